"""MCAP recordings of the daemon's inputs (RGB, depth, pressure) and outputs (force frames).

Channels (protobuf encoding; schemas embedded in the file, so Foxglove and any MCAP reader
decode them):

==============================  ============================  =================================
topic                           schema                        content
==============================  ============================  =================================
/bubble_rt/camera_info          bubble_rt.v1.CameraInfo       intrinsics + camera->mesh pose
/bubble_rt/mesh                 bubble_rt.v1.Mesh             the mesh forces are reported on
/bubble_rt/rgb                  foxglove.CompressedImage      colour image (jpeg or png, by
                                                              ``recording.color``), sequence =
                                                              frame index
/bubble_rt/depth                foxglove.RawImage (32FC1)     depth, metres (0 = invalid)
/bubble_rt/pressure             bubble_rt.v1.PressureSample   pressure paired with the frame
/bubble_rt/wrench               bubble_rt.v1.WrenchSample     force/torque reading of the frame
                                                              (when the frame has one)
/bubble_rt/reference/{rgb,depth,pressure,wrench}              the reference (untouched) frames
/bubble_rt/force                bubble_rt.v1.ForceFrame       estimator output
/bubble_rt/status               bubble_rt.v1.Status           daemon status
==============================  ============================  =================================

Size: chunks are zstd-compressed, which keeps the raw float depth lossless at about 0.14 MB a
frame; with JPEG colour (quality 90) a demo frame takes about 0.26 MB (see
:mod:`bubble_rt.io.image_codec`). Images are encoded on the recorder's thread, never on the
caller's. Recordings written before (colour as RawImage rgb8, lz4 chunks) read the same.

Clock: message log times are capture times on the daemon's wall clock (Unix ns, UTC); the
daemon restamps frames from sources with their own time base (the simulator, replays)
on arrival, reference frames included. The writer never writes a negative time: a time
before the Unix epoch is written as 0 and counted in ``Recorder.clamped``.

Chunks are flushed to disk at least every ``flush_s`` seconds, so after a crash the file is
readable up to the last flushed chunk: every reader here goes through the tolerant reader of
:mod:`bubble_rt.io.mcap_scan` (cut files, damaged chunks; what was lost is reported) and
``bubble-rt recover`` rewrites such a file as a finalised, indexed one.

A write failure (disk full, device gone) never reaches the caller: the recorder stops
writing, keeps the reason in ``Recorder.failed`` and drops (counts) what it is given after.
"""

from __future__ import annotations

import functools
import logging
import os
import queue
import stat
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bubble_rt._validate import file_kind
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame, FrameFault, tolerant
from bubble_rt.io import mcap_scan
from bubble_rt.io.image_codec import color_image, fox_compressed, fox_raw
from bubble_rt.io.image_codec import image_array as image_array  # re-exported
from bubble_rt.io.image_codec import raw_image as raw_image  # re-exported
from bubble_rt.io.mcap_scan import McapFileError, ReadReport, scan
from bubble_rt.io.protocol import pb

fox: Any = fox_raw
log = logging.getLogger("bubble_rt.io.mcap")

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
#: What the estimate depended on besides the frames: the daemon's effective configuration
#: (estimator, flow, solver settings and calibration, live set_params included) as a
#: ControlReply's ``config_toml``, written when recording starts (and after a set_params).
TOPIC_SETTINGS = "/bubble_rt/settings"

_TYPES: dict[str, Any] = {
    "foxglove.RawImage": fox.RawImage,
    "foxglove.CompressedImage": fox_compressed.CompressedImage,
    "bubble_rt.v1.CameraInfo": pb.CameraInfo,
    "bubble_rt.v1.Mesh": pb.Mesh,
    "bubble_rt.v1.PressureSample": pb.PressureSample,
    "bubble_rt.v1.WrenchSample": pb.WrenchSample,
    "bubble_rt.v1.ForceFrame": pb.ForceFrame,
    "bubble_rt.v1.Status": pb.Status,
    "bubble_rt.v1.ControlReply": pb.ControlReply,
}


def _ns(t: float) -> int:
    return int(round(t * 1e9))


class RecordingWarning(UserWarning):
    """A recording was read only in part (not closed, damaged chunks, bad frames)."""


class RecordingPathError(ValueError):
    """A recording cannot be written at this path (exists, not a regular file, no folder)."""


def open_new_file(path: str | Path, overwrite: bool = False) -> Any:
    """Open ``path`` for writing a recording without ever blocking; a binary file object.

    Refused (:class:`RecordingPathError`, with the reason): an existing file unless
    ``overwrite``, anything that is not a regular file (FIFO, device, folder) even with
    ``overwrite``, and a path whose folder does not exist (no folder is created). The open
    is non-blocking (a FIFO without a reader cannot hang the caller) and checked on the open
    descriptor, so a file swapped in between cannot slip through.
    """
    p = Path(path)
    if not p.parent.is_dir():
        what = _under_a_file(p.parent)
        if what is not None:
            raise RecordingPathError(f"{p}: {what} is a file, not a folder")
        raise RecordingPathError(f"{p}: folder {p.parent} does not exist")
    try:
        st = os.stat(p)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise RecordingPathError(f"{p}: {exc.strerror or exc}") from exc
    if st is not None:
        if not stat.S_ISREG(st.st_mode):
            raise RecordingPathError(
                f"{p}: exists and is not a regular file ({file_kind(st.st_mode)})"
            )
        if not overwrite:
            raise RecordingPathError(
                f"{p}: file exists, not overwritten (replace it with --overwrite, "
                "record_start overwrite = true or recording.overwrite = true)"
            )
    flags = os.O_WRONLY | os.O_CREAT | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    flags |= 0 if overwrite else os.O_EXCL
    try:
        fd = os.open(p, flags, 0o644)
    except FileExistsError as exc:
        raise RecordingPathError(f"{p}: file exists (not overwritten)") from exc
    except OSError as exc:
        raise RecordingPathError(f"{p}: cannot open for writing: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise RecordingPathError(f"{p}: not a regular file ({file_kind(st.st_mode)})")
        os.set_blocking(fd, True)
        os.ftruncate(fd, 0)
        return os.fdopen(fd, "wb")
    except BaseException:
        os.close(fd)
        raise


def _under_a_file(folder: Path) -> Path | None:
    """The existing non-folder among ``folder`` and its parents (None if there is none)."""
    for q in (folder, *folder.parents):
        if q.exists():
            return None if q.is_dir() else q
    return None


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


class Recorder:
    """Writes an MCAP recording from a background thread through a bounded queue.

    ``write_*`` never block the caller: when the writer falls behind by ``queue_size``
    messages, new messages are dropped and counted in ``dropped``. All file work (chunks,
    flushes, the summary and footer) happens on the writer thread; the constructor only opens
    the file (:func:`open_new_file`, non-blocking, refusing existing files unless
    ``overwrite``). A write failure sets ``failed`` (the reason) at once and never raises.
    """

    def __init__(
        self,
        path: str | Path,
        camera: Camera | None = None,
        mesh: Any | None = None,
        *,
        inputs: bool = True,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
        color: str = "jpeg",
        jpeg_quality: int = 90,
        queue_size: int = 64,
        flush_s: float = 1.0,
        overwrite: bool = False,
        file: Any = None,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter

        self.path = Path(path)
        self.inputs = inputs
        #: Colour encoding (:data:`bubble_rt.io.image_codec.COLOR_CODECS`) and JPEG quality.
        self.color = color
        self.jpeg_quality = jpeg_quality
        self.flush_s = flush_s
        comp = {
            "lz4": CompressionType.LZ4,
            "zstd": CompressionType.ZSTD,
            "none": CompressionType.NONE,
        }[compression]
        # Buffered; flushed to the OS every flush_s (a flushed chunk survives a crash).
        self._file = file if file is not None else open_new_file(self.path, overwrite)
        self._writer = McapWriter(self._file, chunk_size=chunk_size, compression=comp)
        self._channels: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, Callable[[], Any], int, int] | None] = queue.Queue(
            queue_size
        )
        self.dropped = 0
        self.written = 0
        #: Log times before the Unix epoch written as 0.
        self.clamped = 0
        #: First message that could not be built or encoded (the recording goes on).
        self.error = ""
        #: Why writing stopped (disk full, device gone): the file is incomplete. "" while fine.
        self.failed = ""
        #: Set once the file is finalised (or abandoned after a failure) by the writer thread.
        self.finished = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="recorder", daemon=True)
        self._thread.start()
        if camera is not None:
            self._put(TOPIC_CAMERA_INFO, lambda: camera_info(camera, time.time()), time.time(), 0)
        if mesh is not None:
            self._put(TOPIC_MESH, lambda: mesh, time.time(), 0)

    # ---------------------------------------------------------------- producer side
    def _put(self, topic: str, build: Callable[[], Any], t: float, seq: int) -> bool:
        if self._closed or self.failed:
            if self.failed:
                self.dropped += 1
            return False
        ns = _ns(t)
        if ns < 0:
            self.clamped += 1
            ns = 0
        try:
            self._queue.put_nowait((topic, build, ns, int(seq)))
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
            rgb, codec, q = frame.rgb, self.color, self.jpeg_quality
            # Encoded on the writer thread (the lambda runs there), never the caller's.
            self._put(topics[0], lambda: color_image(rgb, t, codec, q), t, idx)
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

    def _fail(self, exc: BaseException) -> None:
        reason = f"{type(exc).__name__}: {exc}"
        self.failed = f"writing {self.path} failed: {reason}"
        log.error("recording stopped: %s", self.failed)

    def _drain(self) -> None:
        """After a failure: take (and count) what producers still queue, until closed."""
        while not self._closed:
            try:
                if self._queue.get(timeout=0.1) is not None:
                    self.dropped += 1
            except queue.Empty:
                pass

    def _loop(self) -> None:
        try:
            # The header goes to disk at once: an unwritable target fails now, not in 1 s.
            self._writer.start(profile="", library="bubble_rt")
            self._writer.flush()
            self._write_queued()
            self._writer.finish()
            self._file.flush()
        except Exception as exc:  # disk full, device gone: report, never raise
            self._fail(exc)
            self._drain()
        finally:
            try:
                self._file.close()
            except Exception as exc:
                if not self.failed:
                    self._fail(exc)
            self.finished.set()

    def _write_queued(self) -> None:
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
                    data = msg.SerializeToString()
                    cid = self._channel(topic, msg)
                except Exception as exc:  # a bad message: keep recording the rest
                    self.error = self.error or f"{type(exc).__name__}: {exc}"
                else:
                    self._writer.add_message(
                        channel_id=cid,
                        log_time=log_ns,
                        publish_time=log_ns,
                        data=data,
                        sequence=seq & 0xFFFFFFFF,
                    )
                    self.written += 1
            if time.monotonic() - last_flush > self.flush_s:
                self._writer.flush()  # ends the chunk in progress: it survives a crash
                last_flush = time.monotonic()
            if self._closed and self._queue.empty():
                break

    def close(self, timeout: float = 1.5) -> bool:
        """Write what is queued, then the index and footer (on the writer thread).

        Waits at most ``timeout`` seconds; True when the file is finalised (False: still
        writing in the background, or ``failed``). Never raises.
        """
        self._closed = True
        self.finished.wait(timeout)
        return self.finished.is_set() and not self.failed

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def write_recording(
    path: str | Path,
    frames: Iterable[Frame],
    camera: Camera,
    reference: Iterable[Frame] = (),
    overwrite: bool = False,
    color: str = "png",
) -> int:
    """Write frames (and optional reference frames) as a recording; returns frames written.

    Used by anything that produces frames offline (e.g. the simulator); nothing is dropped,
    and the colour is lossless by default (``color``: "png" or "jpeg" at quality 90).
    """
    n = 0
    rec = Recorder(path, camera, queue_size=1 << 30, overwrite=overwrite, color=color)
    try:
        rec.write_reference(reference)
        for f in frames:
            rec.write_frame(f)
            n += 1
    finally:
        rec.close(timeout=600.0)
    if rec.failed:
        raise OSError(rec.failed)
    return n


# ---------------------------------------------------------------------------- reading
def iter_messages(
    path: str | Path, report: ReadReport | None = None
) -> Iterator[tuple[str, Any, int, int]]:
    """(topic, decoded message, log_time ns, sequence) in file order.

    Tolerant (:func:`bubble_rt.io.mcap_scan.scan`): reads files that were not closed (cut by
    a crash), skips damaged chunks and undecodable messages; ``report`` says what was lost.
    Raises :class:`~bubble_rt.io.mcap_scan.McapFileError` for an empty or non-MCAP file.
    """
    report = report if report is not None else ReadReport(str(path))
    schemas: dict[int, Any] = {}
    channels: dict[int, tuple[str, Any]] = {}
    for opcode, r in scan(path, report):
        if opcode == 0x03:
            schemas.setdefault(r.id, _TYPES.get(r.name))
        elif opcode == 0x04:
            channels.setdefault(r.id, (r.topic, schemas.get(r.schema_id)))
        elif opcode == 0x05:
            topic, cls = channels.get(r.channel_id, ("", None))
            if cls is None:
                continue
            msg = cls()
            try:
                msg.ParseFromString(r.data)
            except Exception:
                report.messages_undecodable += 1
                continue
            yield topic, msg, r.log_time, r.sequence


class McapRecording:
    """A recording written by :class:`Recorder`, read back as frames (the replay source).

    Attributes: ``camera`` (from camera_info; D405 default if absent), ``has_reference``,
    ``report`` (:class:`~bubble_rt.io.mcap_scan.ReadReport`: not closed, damaged chunks,
    messages read vs indexed), ``frames_indexed`` (frames the file's index lists; None when
    it has no index). Opening warns (:class:`RecordingWarning`) when the file was not read
    whole. Iterating yields :class:`Frame` objects (t = capture time, seconds) in recorded
    order, and a :class:`~bubble_rt.frames.FrameFault` in place of a frame whose
    messages are damaged (with ``faults=True``; otherwise such frames are skipped).

    Raises :class:`~bubble_rt.io.mcap_scan.McapFileError` for an empty or non-MCAP file and
    for one without any frame.
    """

    def __init__(self, path: str | Path, *, warn: bool = True) -> None:
        self.path = Path(path)
        self.camera = Camera.d405()
        self.mesh: Any | None = None
        #: The daemon's configuration (TOML) when recording started ("" if not recorded).
        self.settings_toml = ""
        #: Frame indices the daemon published forces for (the frames it solved).
        self.published: set[int] = set()
        self._reference: list[Frame] = []
        self._n = 0
        self.report = ReadReport(str(self.path))
        has_camera_info = False
        #: The file has its camera_info (else ``camera`` is the D405 default).
        self.has_camera_info = False
        for topic, msg, _, _ in iter_messages(self.path, self.report):
            if topic == TOPIC_CAMERA_INFO and not has_camera_info:
                try:
                    self.camera = camera_from_info(msg)
                    has_camera_info = True
                except Exception as exc:
                    self.report.problems.append(f"camera_info unreadable: {exc}")
            elif topic == TOPIC_MESH and self.mesh is None:
                self.mesh = msg
            elif topic == TOPIC_PRESSURE:
                self._n += 1
            elif topic == TOPIC_SETTINGS and not self.settings_toml:
                self.settings_toml = msg.config_toml
            elif topic == TOPIC_FORCE:
                self.published.add(int(msg.frame_index))
        self.has_camera_info = has_camera_info
        self.frames_indexed = self.report.topic_indexed.get(TOPIC_PRESSURE)
        if self._n == 0 and self.report.topic_messages.get(TOPIC_REF_PRESSURE, 0) == 0:
            raise McapFileError(f"{self.path}: no frame in the recording ({self.report.summary()})")
        self._reference = [f for f in self._frames(reference=True) if isinstance(f, Frame)]
        if warn and not self.report.complete:
            text = self.report.summary()
            if self.frames_indexed is not None and self._n < self.frames_indexed:
                text += f"; {self._n} of {self.frames_indexed} frames readable"
            warnings.warn(RecordingWarning(text), stacklevel=2)

    @property
    def has_reference(self) -> bool:
        return bool(self._reference)

    def reference_frames(self, n: int) -> list[Frame]:
        return self._reference[:n]

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        return (f for f in self._frames(reference=False) if isinstance(f, Frame))

    def frames(self, faults: bool = True) -> Iterator[Frame | FrameFault]:
        """Frames in order; with ``faults`` a FrameFault stands in for each damaged one."""
        return (f for f in self._frames(reference=False) if faults or isinstance(f, Frame))

    def _frames(self, reference: bool) -> Iterator[Frame | FrameFault]:
        rgb_t, depth_t, p_t = (
            (TOPIC_REF_RGB, TOPIC_REF_DEPTH, TOPIC_REF_PRESSURE)
            if reference
            else (TOPIC_RGB, TOPIC_DEPTH, TOPIC_PRESSURE)
        )
        wrench_t = TOPIC_REF_WRENCH if reference else TOPIC_WRENCH
        partial: dict[int, dict[str, Any]] = {}
        name = self.path.name
        for topic, msg, log_ns, seq in iter_messages(self.path):
            if topic in (rgb_t, depth_t):
                key = "rgb" if topic == rgb_t else "depth"
                try:
                    partial.setdefault(seq, {})[key] = image_array(msg)
                except Exception as exc:
                    partial.setdefault(seq, {}).setdefault("faults", []).append(
                        (
                            f"{topic}: {type(exc).__name__}: {exc}",
                            "colour" if key == "rgb" else "depth",
                        )
                    )
            elif topic == wrench_t:
                partial.setdefault(seq, {})["wrench"] = list(msg.force) + list(msg.torque)
            elif topic == p_t:
                parts = partial.pop(seq, {})
                # Frames are written rgb, depth, pressure: older partial entries are orphans.
                for k in [k for k in partial if k < seq]:
                    del partial[k]
                idx = int(msg.frame_index)
                where = f"{name} frame {idx}"
                if parts.get("faults"):
                    texts, kinds = zip(*parts["faults"], strict=True)
                    kind = kinds[0] if len(set(kinds)) == 1 else "frame"
                    yield FrameFault(idx, where, "; ".join(texts), kind)
                    continue
                yield tolerant(
                    idx,
                    where,
                    functools.partial(
                        Frame,
                        rgb=parts.get("rgb"),
                        depth=parts.get("depth"),
                        pressure_pa=msg.pressure_pa,
                        t=log_ns / 1e9,
                        t_pressure=msg.time_ns / 1e9,
                        index=idx,
                        wrench=parts.get("wrench"),
                    ),
                )

    def force_frames(self) -> Iterator[Any]:
        for topic, msg, _, _ in iter_messages(self.path):
            if topic == TOPIC_FORCE:
                yield msg


def recover(src: str | Path, dst: str | Path, overwrite: bool = False) -> ReadReport:
    """Rewrite ``src`` as a finalised, indexed MCAP file ``dst`` from what is readable.

    Keeps schemas, channels and every readable message (log and publish times, sequence);
    returns the :class:`ReadReport` of reading ``src``.
    """
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    report = ReadReport(str(src))
    records = scan(src, report)  # refuses a non-MCAP source before dst is created
    first = next(records, None)
    fh = open_new_file(dst, overwrite=overwrite)
    try:
        writer = McapWriter(fh, compression=CompressionType.LZ4)
        writer.start(profile=_profile(src), library="bubble_rt recover")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        pending: dict[int, Any] = {}
        seen_channels: set[int] = set()
        for opcode, rec in _chain(first, records):
            if opcode == mcap_scan.SCHEMA and rec.id not in schemas:
                schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
            elif opcode == mcap_scan.CHANNEL and rec.id not in seen_channels:
                seen_channels.add(rec.id)
                pending[rec.id] = rec
            elif opcode == mcap_scan.MESSAGE:
                cid = channels.get(rec.channel_id)
                if cid is None:
                    ch = pending.get(rec.channel_id)
                    if ch is None or (ch.schema_id and ch.schema_id not in schemas):
                        report.messages_undecodable += 1
                        continue
                    cid = channels[rec.channel_id] = writer.register_channel(
                        ch.topic, ch.message_encoding, schemas.get(ch.schema_id, 0), ch.metadata
                    )
                writer.add_message(
                    cid, rec.log_time, rec.data, rec.publish_time, sequence=rec.sequence
                )
        writer.finish()
    finally:
        fh.close()
    return report


def _profile(path: str | Path) -> str:
    """The MCAP header's profile ("ros2" for a ROS 2 bag), kept by :func:`recover`."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            return str(make_reader(fh).get_header().profile)
    except Exception:  # a damaged header: the records are still worth recovering
        return ""


def _chain(first: Any, rest: Iterator[Any]) -> Iterator[Any]:
    if first is not None:
        yield first
    yield from rest
