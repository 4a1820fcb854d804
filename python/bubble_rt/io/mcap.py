"""MCAP recordings of the daemon's inputs (RGB, depth, pressure) and outputs (force frames).

Channels (protobuf encoding; schemas embedded in the file, so Foxglove and any MCAP reader
decode them):

==============================  ============================  =================================
topic                           schema                        content
==============================  ============================  =================================
/bubble_rt/camera_info          bubble_rt.v1.CameraInfo       intrinsics + camera->mesh pose
/bubble_rt/mesh                 bubble_rt.v1.Mesh             the mesh forces are reported on
/bubble_rt/rgb                  foxglove.RawImage (rgb8)      colour image, sequence = frame idx
/bubble_rt/depth                foxglove.RawImage (32FC1)     depth, metres (0 = invalid)
/bubble_rt/pressure             bubble_rt.v1.PressureSample   pressure paired with the frame
/bubble_rt/wrench               bubble_rt.v1.WrenchSample     force/torque reading of the frame
                                                              (when the frame has one)
/bubble_rt/reference/{rgb,depth,pressure,wrench}              the reference (untouched) frames
/bubble_rt/force                bubble_rt.v1.ForceFrame       estimator output
/bubble_rt/status               bubble_rt.v1.Status           daemon status
==============================  ============================  =================================

Message log times are the capture times (Unix ns). Chunks are flushed to disk at least every
``flush_s`` seconds, so after a crash the file is readable up to the last flushed chunk with
:class:`McapRecording` (which stops cleanly at a truncated tail).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.io.protocol import pb
from bubble_rt.proto_gen.bubble_rt.v1 import foxglove_raw_image_pb2 as _fox

fox: Any = _fox

TOPIC_CAMERA_INFO = "/bubble_rt/camera_info"
TOPIC_MESH = "/bubble_rt/mesh"
TOPIC_RGB = "/bubble_rt/rgb"
TOPIC_DEPTH = "/bubble_rt/depth"
TOPIC_PRESSURE = "/bubble_rt/pressure"
TOPIC_REF_RGB = "/bubble_rt/reference/rgb"
TOPIC_REF_DEPTH = "/bubble_rt/reference/depth"
TOPIC_REF_PRESSURE = "/bubble_rt/reference/pressure"
TOPIC_WRENCH = "/bubble_rt/wrench"
TOPIC_REF_WRENCH = "/bubble_rt/reference/wrench"
TOPIC_FORCE = "/bubble_rt/force"
TOPIC_STATUS = "/bubble_rt/status"
FRAME_ID = "bubble_rt_camera"

_TYPES: dict[str, Any] = {
    "foxglove.RawImage": fox.RawImage,
    "bubble_rt.v1.CameraInfo": pb.CameraInfo,
    "bubble_rt.v1.Mesh": pb.Mesh,
    "bubble_rt.v1.PressureSample": pb.PressureSample,
    "bubble_rt.v1.WrenchSample": pb.WrenchSample,
    "bubble_rt.v1.ForceFrame": pb.ForceFrame,
    "bubble_rt.v1.Status": pb.Status,
}


def _ns(t: float) -> int:
    return int(round(t * 1e9))


def camera_info(camera: Camera, t: float = 0.0) -> Any:
    msg = pb.CameraInfo(
        time_ns=_ns(t),
        width=camera.width,
        height=camera.height,
        fx=camera.fx,
        fy=camera.fy,
        cx=camera.cx,
        cy=camera.cy,
    )
    msg.distortion.extend(list(camera.distortion))
    msg.pose.extend(camera.pose_matrix.ravel().tolist())
    return msg


def camera_from_info(msg: Any) -> Camera:
    return Camera(
        fx=msg.fx,
        fy=msg.fy,
        cx=msg.cx,
        cy=msg.cy,
        width=msg.width,
        height=msg.height,
        distortion=tuple(msg.distortion) or (0.0,) * 5,
        pose=tuple(tuple(r) for r in np.asarray(msg.pose, dtype=np.float64).reshape(4, 4)),
    )


def raw_image(img: np.ndarray, t: float) -> Any:
    """A foxglove.RawImage of an RGB uint8 (rgb8) or depth float32 (32FC1) image."""
    a = np.ascontiguousarray(img)
    enc = "rgb8" if a.ndim == 3 else "32FC1"
    if enc == "32FC1":
        a = a.astype("<f4", copy=False)
    msg = fox.RawImage(
        frame_id=FRAME_ID,
        width=a.shape[1],
        height=a.shape[0],
        encoding=enc,
        step=a.strides[0],
        data=a.tobytes(),
    )
    ns = _ns(t)
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)
    return msg


def image_array(msg: Any) -> np.ndarray:
    if msg.encoding == "rgb8":
        return np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, 3).copy()
    if msg.encoding == "32FC1":
        return np.frombuffer(msg.data, dtype="<f4").reshape(msg.height, msg.width).copy()
    if msg.encoding == "16UC1":  # millimetres, as some tools write depth
        d = np.frombuffer(msg.data, dtype="<u2").reshape(msg.height, msg.width)
        return (d.astype(np.float32) / 1000.0).copy()
    raise ValueError(f"unsupported image encoding {msg.encoding!r}")


class Recorder:
    """Writes an MCAP recording from a background thread through a bounded queue.

    ``write_*`` never block the caller: when the writer falls behind by ``queue_size``
    messages, new messages are dropped and counted in ``dropped``.
    """

    def __init__(
        self,
        path: str | Path,
        camera: Camera | None = None,
        mesh: Any | None = None,
        *,
        inputs: bool = True,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "lz4",
        queue_size: int = 64,
        flush_s: float = 1.0,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.inputs = inputs
        self.flush_s = flush_s
        comp = {
            "lz4": CompressionType.LZ4,
            "zstd": CompressionType.ZSTD,
            "none": CompressionType.NONE,
        }[compression]
        # Buffered; flushed to the OS every flush_s (a flushed chunk survives a crash).
        self._file = open(self.path, "wb")  # noqa: SIM115
        self._writer = McapWriter(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile="", library="bubble_rt")
        self._channels: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, Callable[[], Any], int, int] | None] = queue.Queue(
            queue_size
        )
        self.dropped = 0
        self.written = 0
        self.error = ""
        self._closed = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name="recorder", daemon=True)
        self._thread.start()
        if camera is not None:
            self._put(TOPIC_CAMERA_INFO, lambda: camera_info(camera, time.time()), time.time(), 0)
        if mesh is not None:
            self._put(TOPIC_MESH, lambda: mesh, time.time(), 0)

    # ---------------------------------------------------------------- producer side
    def _put(self, topic: str, build: Callable[[], Any], t: float, seq: int) -> bool:
        if self._closed:
            return False
        try:
            # MCAP log times are unsigned: the simulator's reference frames have t < 0.
            self._queue.put_nowait((topic, build, max(_ns(t), 0), int(seq)))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def write_frame(self, frame: Frame, reference: bool = False) -> None:
        """Record one input frame (RGB, depth, pressure), sequence = ``frame.index``."""
        if not self.inputs:
            return
        topics = (
            (TOPIC_REF_RGB, TOPIC_REF_DEPTH, TOPIC_REF_PRESSURE)
            if reference
            else (TOPIC_RGB, TOPIC_DEPTH, TOPIC_PRESSURE)
        )
        t, idx = frame.t, frame.index
        if frame.rgb is not None:
            rgb = frame.rgb
            self._put(topics[0], lambda: raw_image(rgb, t), t, idx)
        if frame.depth is not None:
            depth = frame.depth
            self._put(topics[1], lambda: raw_image(depth, t), t, idx)
        if frame.wrench is not None:  # before the pressure, which completes the frame
            w = [float(x) for x in frame.wrench]
            self._put(
                TOPIC_REF_WRENCH if reference else TOPIC_WRENCH,
                lambda: pb.WrenchSample(time_ns=_ns(t), frame_index=idx, force=w[:3], torque=w[3:]),
                t,
                idx,
            )
        p = float(frame.pressure_pa)
        tp = frame.t_pressure if frame.t_pressure is not None else t
        self._put(
            topics[2],
            lambda: pb.PressureSample(time_ns=_ns(tp), pressure_pa=p, frame_index=idx),
            t,
            idx,
        )

    def write_reference(self, frames: Iterable[Frame]) -> None:
        for f in frames:
            self.write_frame(f, reference=True)

    def write_message(self, topic: str, msg: Any, t: float | None = None, seq: int = 0) -> None:
        self._put(topic, lambda: msg, time.time() if t is None else t, seq)

    def write_force(self, msg: Any) -> None:
        self._put(TOPIC_FORCE, lambda: msg, msg.capture_time_ns / 1e9, msg.frame_index)

    def write_status(self, msg: Any) -> None:
        self._put(TOPIC_STATUS, lambda: msg, msg.time_ns / 1e9, 0)

    # ---------------------------------------------------------------- writer thread
    def _channel(self, topic: str, msg: Any) -> int:
        cid = self._channels.get(topic)
        if cid is None and hasattr(msg, "schema_name"):  # pre-encoded (bubble_rt.io.foxglove)
            sid = self._writer.register_schema(
                name=msg.schema_name, encoding=msg.schema_encoding, data=msg.schema_data
            )
            cid = self._writer.register_channel(
                topic=topic, message_encoding=msg.message_encoding, schema_id=sid
            )
            self._channels[topic] = cid
        if cid is None:
            from mcap.well_known import MessageEncoding
            from mcap_protobuf.schema import register_schema

            sid = register_schema(self._writer, type(msg))
            cid = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=sid
            )
            self._channels[topic] = cid
        return cid

    def _loop(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                item = None
                if self._closed:
                    break
            if item is not None:
                topic, build, log_ns, seq = item
                try:
                    msg = build()
                    with self._lock:
                        self._writer.add_message(
                            channel_id=self._channel(topic, msg),
                            log_time=log_ns,
                            publish_time=log_ns,
                            data=msg.SerializeToString(),
                            sequence=seq & 0xFFFFFFFF,
                        )
                    self.written += 1
                except Exception as exc:  # keep recording the rest; report the first fault
                    self.error = self.error or f"{type(exc).__name__}: {exc}"
            if time.monotonic() - last_flush > self.flush_s:
                with self._lock:
                    self._writer.flush()
                last_flush = time.monotonic()
            if self._closed and self._queue.empty():
                break

    def close(self, timeout: float = 1.5) -> None:
        """Write what is queued (within ``timeout``), then the index and footer."""
        if self._closed:
            return
        self._closed = True
        self._thread.join(timeout)
        with self._lock:
            try:
                self._writer.finish()
                self._file.flush()
            finally:
                self._file.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def write_recording(
    path: str | Path,
    frames: Iterable[Frame],
    camera: Camera,
    reference: Iterable[Frame] = (),
) -> int:
    """Write frames (and optional reference frames) as a recording; returns frames written.

    Used by anything that produces frames offline (e.g. the simulator); nothing is dropped.
    """
    n = 0
    rec = Recorder(path, camera, queue_size=1 << 30)
    try:
        rec.write_reference(reference)
        for f in frames:
            rec.write_frame(f)
            n += 1
    finally:
        rec.close(timeout=600.0)
    return n


# ---------------------------------------------------------------------------- reading
def iter_messages(path: str | Path) -> Iterator[tuple[str, Any, int, int]]:
    """(topic, decoded message, log_time ns, sequence) in file order.

    Stops quietly at a truncated tail (a recording cut short by a crash).
    """
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Any] = {}
    channels: dict[int, tuple[str, Any]] = {}
    with open(path, "rb") as f:
        reader = StreamReader(f, record_size_limit=1 << 30)
        it = iter(reader.records)
        while True:
            try:
                rec = next(it)
            except StopIteration:
                return
            except Exception:
                return  # truncated or corrupt tail: everything before it was delivered
            kind = type(rec).__name__
            r: Any = rec
            if kind == "Schema":
                schemas[r.id] = _TYPES.get(r.name)
            elif kind == "Channel":
                channels[r.id] = (r.topic, schemas.get(r.schema_id))
            elif kind == "Message":
                topic, cls = channels.get(r.channel_id, ("", None))
                if cls is None:
                    continue
                msg = cls()
                msg.ParseFromString(r.data)
                yield topic, msg, r.log_time, r.sequence


class McapRecording:
    """A recording written by :class:`Recorder`, read back as frames (the replay source).

    Attributes: ``camera`` (from camera_info; D405 default if absent), ``has_reference``.
    Iterating yields :class:`Frame` objects (t = capture time, seconds) in recorded order.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.camera = Camera.d405()
        self.mesh: Any | None = None
        self._reference: list[Frame] = []
        self._n = 0
        for topic, msg, _, _ in iter_messages(self.path):
            if topic == TOPIC_CAMERA_INFO:
                self.camera = camera_from_info(msg)
            elif topic == TOPIC_MESH and self.mesh is None:
                self.mesh = msg
            elif topic == TOPIC_PRESSURE:
                self._n += 1
        self._reference = list(self._frames(reference=True))

    @property
    def has_reference(self) -> bool:
        return bool(self._reference)

    def reference_frames(self, n: int) -> list[Frame]:
        return self._reference[:n]

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        return self._frames(reference=False)

    def _frames(self, reference: bool) -> Iterator[Frame]:
        rgb_t, depth_t, p_t = (
            (TOPIC_REF_RGB, TOPIC_REF_DEPTH, TOPIC_REF_PRESSURE)
            if reference
            else (TOPIC_RGB, TOPIC_DEPTH, TOPIC_PRESSURE)
        )
        wrench_t = TOPIC_REF_WRENCH if reference else TOPIC_WRENCH
        partial: dict[int, dict[str, Any]] = {}
        for topic, msg, log_ns, seq in iter_messages(self.path):
            if topic == rgb_t:
                partial.setdefault(seq, {})["rgb"] = image_array(msg)
            elif topic == depth_t:
                partial.setdefault(seq, {})["depth"] = image_array(msg)
            elif topic == wrench_t:
                partial.setdefault(seq, {})["wrench"] = list(msg.force) + list(msg.torque)
            elif topic == p_t:
                parts = partial.pop(seq, {})
                # Frames are written rgb, depth, pressure: older partial entries are orphans.
                for k in [k for k in partial if k < seq]:
                    del partial[k]
                yield Frame(
                    rgb=parts.get("rgb"),
                    depth=parts.get("depth"),
                    pressure_pa=msg.pressure_pa,
                    t=log_ns / 1e9,
                    t_pressure=msg.time_ns / 1e9,
                    index=int(msg.frame_index),
                    wrench=parts.get("wrench"),
                )

    def force_frames(self) -> Iterator[Any]:
        for topic, msg, _, _ in iter_messages(self.path):
            if topic == TOPIC_FORCE:
                yield msg
