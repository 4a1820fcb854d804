"""ROS 2 message types and conversions for bags: the type names and topics bubble_rt reads and
writes, the rosbags type store, and images, camera info and poses to and from messages
(used by :mod:`bubble_rt.io.rosbag` to read and :mod:`bubble_rt.io.bag_writer` to write)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.frames import FrameError

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
FLOAT32 = "std_msgs/msg/Float32"
WRENCH = "geometry_msgs/msg/WrenchStamped"
TF = "tf2_msgs/msg/TFMessage"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"

SENSOR_FRAME = "bubble_rt_sensor"
TOPIC_WRENCH = "/bubble_rt/wrench"
TOPIC_NODES = "/bubble_rt/nodes"
#: PointCloud2 fields written by :class:`BagWriter`, in order (all FLOAT32).
NODE_FIELDS = ("x", "y", "z", "fx", "fy", "fz", "pressure", "contact")
PRESSURE_DELAY_S = 0.010
ROLES = ("color", "depth", "info", "pressure", "wrench")


def typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def image_to_array(msg: Any, depth_unit: float = 0.001) -> NDArray:
    """RGB uint8 (rgb8/bgr8/rgba8/bgra8/mono8) or depth float32 metres (16UC1/mono16, 32FC1)."""
    h, w, enc = int(msg.height), int(msg.width), str(msg.encoding).lower()
    data = np.asarray(msg.data, dtype=np.uint8)
    step = int(msg.step)
    big = bool(msg.is_bigendian)
    chans = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc3": 3}
    depth_bytes = {"16uc1": 2, "mono16": 2, "32fc1": 4}
    if enc not in chans and enc not in depth_bytes:
        raise FrameError(f"unsupported image encoding {msg.encoding!r}")
    kind = "colour" if enc in chans else "depth"
    row = w * (chans[enc] if enc in chans else depth_bytes[enc])
    if h <= 0 or w <= 0:
        raise FrameError(f"{enc} image is {w} x {h}", kind)
    if step < row:
        raise FrameError(f"{enc} row step {step} bytes is less than {w} pixels need ({row})", kind)
    if data.size < h * step:
        raise FrameError(
            f"{enc} data is {data.size} bytes, {h} rows of {step} need {h * step} (cut short)",
            kind,
        )
    if enc in chans:
        c = chans[enc]
        a = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
        if enc in ("bgr8", "bgra8", "8uc3"):
            a = a[:, :, 2::-1] if c >= 3 else a
        elif c == 4:
            a = a[:, :, :3]
        if c == 1:
            a = np.repeat(a, 3, axis=2)
        return np.ascontiguousarray(a)
    if enc in ("16uc1", "mono16"):
        dt = np.dtype(">u2" if big else "<u2")
        raw = data[: h * step].reshape(h, step)[:, : w * 2].copy().view(dt).reshape(h, w)
        return raw.astype(np.float32) * np.float32(depth_unit)
    if enc == "32fc1":
        dtf = np.dtype(">f4" if big else "<f4")
        d = data[: h * step].reshape(h, step)[:, : w * 4].copy().view(dtf).reshape(h, w)
        d = d.astype(np.float32)
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(d) & (d > 0), d, np.float32(0))
    raise AssertionError(enc)  # every encoding in chans / depth_bytes is decoded above


def camera_from_info(msg: Any) -> Camera:
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        raise FrameError(f"camera_info: k is not a camera matrix ({k.tolist()})")
    d = [float(x) for x in np.asarray(msg.d, dtype=np.float64).reshape(-1)]
    model = str(msg.distortion_model or "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial", "") and any(d):
        raise FrameError(f"camera_info: distortion model {model!r} is not supported")
    dist = tuple((d + [0.0] * 5)[:5])
    return Camera(
        fx=float(k[0]),
        fy=float(k[4]),
        cx=float(k[2]),
        cy=float(k[5]),
        width=int(msg.width),
        height=int(msg.height),
        distortion=dist,  # type: ignore[arg-type]
    )


def quat_matrix(q: Any) -> NDArray[np.float64]:
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    n = np.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_quat(R: NDArray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return float(x), float(y), float(z), float(w)


def decode_image(reader: Any, raw: bytes, msgtype: str, depth_unit: float | None) -> Any:
    """The image of a raw message (colour when ``depth_unit`` is None), or the exception
    decoding it raised, kept for the frame that needs it (which becomes a FrameFault)."""
    kind = "colour" if depth_unit is None else "depth"
    try:
        msg = reader.deserialize(raw, msgtype)
        if depth_unit is None:
            return image_to_array(msg)
        return image_to_array(msg, depth_unit)
    except FrameError as exc:
        return FrameError(f"{kind} image: {exc}", kind)
    except Exception as exc:
        return FrameError(f"{kind} image: {type(exc).__name__}: {exc}", kind)


def stamped_header(ts: Any, t: float, frame_id: str) -> Any:
    ns = int(round(t * 1e9))
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(
        stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id
    )
