"""Images in recordings: Foxglove's image messages to and from numpy arrays.

Colour goes in as ``foxglove.CompressedImage``: JPEG at a quality (lossy, the default: about
0.12 MB per 640 x 480 frame at quality 90) or PNG (lossless, about 0.6 MB on the noisy demo
scene). Depth goes in as ``foxglove.RawImage`` 32FC1 (metres) and is compressed losslessly by
the recording's zstd chunks (about 0.14 MB per frame on the demo scene). A 16-bit PNG of the
depth in its sensor unit was measured against that and not kept: it is lossless only where
every pixel lies on the unit's grid (the simulator's mixed edge pixels do not), and where it is
(the real D405 frames) it saves 0.03 MB per frame for 2.4 times the CPU
(docs/bags-and-foxglove.md, "Recording size").

Reading takes every encoding any version wrote (RawImage rgb8, 32FC1, 16UC1 in millimetres;
CompressedImage jpeg or png). An image that cannot be decoded raises :class:`ImageDecodeError`
(a ValueError): the recording reader turns it into a skipped, counted bad frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.io.codec_names import COLOR_CODECS
from bubble_rt.proto_gen.bubble_rt.v1 import foxglove_compressed_image_pb2 as _fox_c
from bubble_rt.proto_gen.bubble_rt.v1 import foxglove_raw_image_pb2 as _fox_r

fox_raw: Any = _fox_r
fox_compressed: Any = _fox_c

#: Frame of reference of every image (the camera's optical frame).
FRAME_ID = "bubble_rt_camera"
_JPEG_EOI = b"\xff\xd9"


class ImageDecodeError(ValueError):
    """An image message that does not decode to an image (corrupt, cut short, unknown)."""


def _stamp(msg: Any, t: float) -> None:
    ns = int(round(t * 1e9))
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)


def raw_image(img: NDArray[Any], t: float) -> Any:
    """A foxglove.RawImage of an RGB uint8 (rgb8) or depth float32 (32FC1) image; ``t`` in s."""
    a = np.ascontiguousarray(img)
    enc = "rgb8" if a.ndim == 3 else "32FC1"
    if enc == "32FC1":
        a = a.astype("<f4", copy=False)
    msg = fox_raw.RawImage(
        frame_id=FRAME_ID,
        width=a.shape[1],
        height=a.shape[0],
        encoding=enc,
        step=a.strides[0],
        data=a.tobytes(),
    )
    _stamp(msg, t)
    return msg


def color_image(rgb: NDArray[np.uint8], t: float, codec: str, jpeg_quality: int = 90) -> Any:
    """A foxglove.CompressedImage of an H x W x 3 uint8 RGB image.

    ``codec`` one of :data:`COLOR_CODECS`: "jpeg" at ``jpeg_quality`` (1-100) or "png"
    (lossless; zlib level 1, Huffman-only: the fastest and, on sensor noise, the smallest).
    """
    import cv2

    bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)
    if codec == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    elif codec == "png":
        params = [
            cv2.IMWRITE_PNG_COMPRESSION,
            1,
            cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
        ]
        ok, buf = cv2.imencode(".png", bgr, params)
    else:
        raise ValueError(f"colour codec {codec!r} is not one of {', '.join(COLOR_CODECS)}")
    if not ok:
        raise ValueError(f"{codec} encoding of a {rgb.shape} image failed")
    msg = fox_compressed.CompressedImage(frame_id=FRAME_ID, format=codec, data=buf.tobytes())
    _stamp(msg, t)
    return msg


def image_array(msg: Any) -> NDArray[Any]:
    """The image of a RawImage or CompressedImage message: H x W x 3 uint8 RGB for colour,
    H x W float32 metres for depth. Raises :class:`ImageDecodeError` when it does not decode."""
    if hasattr(msg, "format"):
        return _decode_compressed(msg.format, bytes(msg.data))
    h, w = int(msg.height), int(msg.width)
    try:
        if msg.encoding == "rgb8":
            return np.frombuffer(msg.data, dtype=np.uint8).reshape(h, w, 3).copy()
        if msg.encoding == "32FC1":
            return np.frombuffer(msg.data, dtype="<f4").reshape(h, w).copy()
        if msg.encoding == "16UC1":  # millimetres, as some tools write depth
            d = np.frombuffer(msg.data, dtype="<u2").reshape(h, w)
            return d.astype(np.float32) / np.float32(1000.0)
    except ValueError as exc:  # data not width x height (cut short, padded rows)
        raise ImageDecodeError(f"{msg.encoding} image: {exc}") from exc
    raise ImageDecodeError(f"unsupported image encoding {msg.encoding!r}")


def _decode_compressed(fmt: str, data: bytes) -> NDArray[np.uint8]:
    import cv2

    fmt = fmt.lower()
    if fmt not in ("jpeg", "jpg", "png"):
        raise ImageDecodeError(f"unsupported compressed image format {fmt!r}")
    # libjpeg decodes a cut JPEG with a warning (the rest grey): its end marker must be there.
    if fmt in ("jpeg", "jpg") and not data.rstrip(b"\x00").endswith(_JPEG_EOI):
        raise ImageDecodeError(f"{fmt} image cut short ({len(data)} bytes, no end marker)")
    buf = np.frombuffer(data, dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise ImageDecodeError(f"{fmt} image does not decode ({len(data)} bytes)")
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), dtype=np.uint8)
