"""MCAP recordings of the daemon's inputs (RGB, depth, pressure) and outputs (force frames):
their channels, reading them back (:class:`McapRecording`) and :func:`recover`. The writer is
:mod:`bubble_rt.io.mcap_writer`.

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
/bubble_rt/rezero               bubble_rt.v1.RezeroEvent      a re-zero step (the reference
                                                              followed the drift; a replay
                                                              applies the same steps)
==============================  ============================  =================================

Size: chunks are zstd-compressed, which keeps the raw float depth lossless at about 0.14 MB a
frame; with JPEG colour (quality 90) a demo frame takes about 0.26 MB (see
:mod:`bubble_rt.io.image_codec`). Recordings written before (colour as RawImage rgb8, lz4
chunks) read the same.

Clock: message log times are capture times on the daemon's wall clock (Unix ns, UTC); the
daemon restamps frames from sources with their own time base (the simulator, replays)
on arrival, reference frames included (the writer clamps a time before the Unix epoch to 0).

The writer flushes chunks to disk at least every ``flush_s`` seconds, so after a crash the file
is readable up to the last flushed chunk: every reader here goes through the tolerant reader of
:mod:`bubble_rt.io.mcap_scan` (cut files, damaged chunks; what was lost is reported) and
``bubble-rt recover`` rewrites such a file as a finalised, indexed one.
"""

from __future__ import annotations

import functools
import os
import stat
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bubble_rt._validate import file_kind
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame, FrameFault, tolerant
from bubble_rt.io import mcap_scan
from bubble_rt.io.image_codec import fox_compressed, fox_raw, image_array
from bubble_rt.io.mcap_scan import McapFileError, ReadReport, scan
from bubble_rt.io.protocol import pb

fox: Any = fox_raw

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
TOPIC_REZERO = "/bubble_rt/rezero"
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
    "bubble_rt.v1.RezeroEvent": pb.RezeroEvent,
}


def to_ns(t: float) -> int:
    """Seconds -> integer nanoseconds (a log time)."""
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
        time_ns=to_ns(t),
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
    """A recording written by :class:`~bubble_rt.io.mcap_writer.Recorder`, read back as frames
    (the replay source).

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
        #: The daemon's re-zero steps (RezeroEvent messages, in recorded order).
        self.rezero: list[Any] = []
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
            elif topic == TOPIC_REZERO:
                self.rezero.append(msg)
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
    def layout(self) -> str:
        """What ``profile = "auto"`` reads (``bubble_rt.sensor.profile_for_layout``): the sensor
        profile the recording's daemon ran with ("sim", "punyo"; its settings name it), so a
        recorded Punyo is estimated as a Punyo offline too; "mcap" when the settings name none
        (or do not parse)."""
        import tomllib

        from bubble_rt.sensor import PROFILES

        try:
            est = tomllib.loads(self.settings_toml).get("estimator", {})
        except tomllib.TOMLDecodeError:
            return "mcap"
        name = est.get("profile") if isinstance(est, dict) else None
        return name if isinstance(name, str) and name in PROFILES else "mcap"

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
