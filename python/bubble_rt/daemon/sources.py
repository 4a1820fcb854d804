"""Capture sources for the daemon: one thread each, feeding bounded mailboxes.

Camera sources (:class:`~bubble_rt.daemon.sim_camera.SimCamera`, :class:`ReplayCamera`, and the devices'
:class:`~bubble_rt.daemon.devices.RealSenseCamera`) put
:class:`~bubble_rt.frames.Frame` objects into a :class:`Mailbox` (``STAGE_FRAMES`` items: a
frame arriving at a full slot replaces the oldest unconsumed one, which is counted as dropped). Pressure sources
(:class:`~bubble_rt.daemon.devices.SerialPressure`, :class:`ConstantPressure`, or the pressure carried by sim/replay
frames) feed a :class:`PressureBuffer`, a fixed-size ring of (time, pascals) samples that
:func:`pair_pressure` interpolates at each camera frame's capture time.

Clock: every sample is stamped on arrival with the daemon's wall clock (``time.time()``,
seconds), so camera and pressure from different devices share one time base and end-to-end
latency (capture -> publish) is meaningful to subscribers on the same host. Reference frames
a source provides (the simulator's, a recording's) are restamped the same way
(:func:`restamp_reference`): nothing downstream, recordings included, sees another clock.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any, Generic, TypeVar

import numpy as np

from bubble_rt.camera import Camera
from bubble_rt.frames import FaultTally, Frame, FrameFault, fault_of

T = TypeVar("T")
log = logging.getLogger("bubble_rt.daemon.sources")
HPA = 100.0


class SourceError(RuntimeError):
    """A source cannot start or lost its device; the message says what to do."""


# ------------------------------------------------------------------------------ slots
#: Frames a stage's mailbox holds (the camera's, and the one between the daemon's stages): a
#: frame that arrives while the stage is busy waits behind at most one other, so one slow frame
#: (a hard solve, a busy host) delays the next instead of losing it; a third replaces the
#: oldest (a drop), so the latency stays bounded when the stage cannot keep up.
STAGE_FRAMES = 2


class Mailbox(Generic[T]):
    """A bounded mailbox, oldest first: ``put`` on a full one replaces its oldest unconsumed
    item (counted in ``dropped``).

    With ``put(block=True)`` the producer waits instead until the consumer made room (lossless
    replay). Never grows past ``capacity``: the daemon works on recent data.
    """

    def __init__(self, capacity: int = 1) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self._cond = threading.Condition()
        self._items: deque[T] = deque()
        self._closed = False
        self.put_count = 0
        self.dropped = 0

    def put(self, item: T, block: bool = False, stop: threading.Event | None = None) -> bool:
        """Store ``item``; returns False if an older item was dropped (or the slot closed)."""
        with self._cond:
            if block:
                while (
                    len(self._items) >= self.capacity
                    and not self._closed
                    and not (stop is not None and stop.is_set())
                ):
                    self._cond.wait(0.05)
            if self._closed:
                return False
            dropped = len(self._items) >= self.capacity
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self.put_count += 1
            self._cond.notify_all()
            return not dropped

    def get(self, timeout: float) -> T | None:
        """Take the oldest item, waiting up to ``timeout`` seconds; None when nothing arrived."""
        with self._cond:
            if not self._items:
                self._cond.wait_for(lambda: bool(self._items) or self._closed, timeout)
            if not self._items:
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def keep_newest(self) -> int:
        """Discard every waiting item but the newest (counted in ``dropped``); how many."""
        with self._cond:
            n = max(0, len(self._items) - 1)
            for _ in range(n):
                self._items.popleft()
            self.dropped += n
            if n:
                self._cond.notify_all()
            return n

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class PressureBuffer:
    """Thread-safe ring of (t seconds, pressure Pa) samples, interpolated at query times."""

    def __init__(self, capacity: int = 512) -> None:
        self._lock = threading.Lock()
        self._t: deque[float] = deque(maxlen=capacity)
        self._p: deque[float] = deque(maxlen=capacity)

    def push(self, t: float, pressure_pa: float) -> None:
        with self._lock:
            if self._t and t < self._t[-1]:
                return  # out-of-order arrival: keep the ring sorted for interpolation
            self._t.append(float(t))
            self._p.append(float(pressure_pa))

    def __len__(self) -> int:
        return len(self._t)

    def at(self, t: float) -> tuple[float, float, float] | None:
        """(pressure Pa, sample time, age s) at time ``t``; None when empty.

        Inside the sampled span: linear interpolation between the bracketing samples (age 0).
        Outside it: the nearest sample is held, ``age`` is the distance to it.
        """
        with self._lock:
            if not self._t:
                return None
            ts = np.fromiter(self._t, dtype=np.float64, count=len(self._t))
            ps = np.fromiter(self._p, dtype=np.float64, count=len(self._p))
        if t >= ts[-1]:
            return float(ps[-1]), float(ts[-1]), float(t - ts[-1])
        if t <= ts[0]:
            return float(ps[0]), float(ts[0]), float(ts[0] - t)
        i = int(np.searchsorted(ts, t))
        t0, t1 = ts[i - 1], ts[i]
        w = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        return float(ps[i - 1] + w * (ps[i] - ps[i - 1])), float(t), 0.0


class ConstantPressure(PressureBuffer):
    """A pressure source that always reads the same value (no sensor; dp is then 0)."""

    name = "constant"

    def __init__(self, pressure_pa: float) -> None:
        super().__init__(1)
        self.value = float(pressure_pa)
        self.stats = SourceStats(self.name)

    def at(self, t: float) -> tuple[float, float, float] | None:
        return self.value, t, 0.0


def pair_pressure(
    frame: Frame, buffer: PressureBuffer, stale_timeout_s: float
) -> tuple[Frame, list[str]]:
    """The frame with ``pressure_pa`` interpolated at its capture time, and degraded reasons.

    Reasons: "no pressure reading" (empty buffer) or "pressure stale (<age> ms)" when the
    nearest reading is more than ``stale_timeout_s`` away from the capture time.
    """
    got = buffer.at(frame.t)
    if got is None:
        return frame, ["no pressure reading"]
    p, t_sample, age = got
    reasons = []
    if age > stale_timeout_s:
        reasons.append(f"pressure stale ({age * 1e3:.0f} ms)")
    return replace(frame, pressure_pa=p, t_pressure=t_sample), reasons


# ------------------------------------------------------------------------------ threads
@dataclass
class SourceStats:
    """Counters of one source: samples delivered, errors by kind, last error text."""

    name: str
    received: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    last_error: str = ""
    last_error_time: float = 0.0
    last_time: float = 0.0
    connected: bool = False

    def error(self, kind: str, text: str) -> None:
        self.errors[kind] = self.errors.get(kind, 0) + 1
        self.last_error = text
        self.last_error_time = time.time()

    @property
    def n_errors(self) -> int:
        return sum(self.errors.values())

    def age(self, now: float) -> float:
        return now - self.last_time if self.last_time else -1.0


class ThreadedSource:
    """Base: runs ``_run`` in a daemon thread, restarting it after errors (reconnect)."""

    name = "source"
    retry_s = 0.5

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = SourceStats(self.name)
        #: Set when a finite source ended (no loop): the daemon may stop.
        self.finished = threading.Event()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name=f"src-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _main(self) -> None:
        while not self._stop.is_set():
            try:
                if self._run() is False:
                    self.finished.set()
                    return
            except Exception as exc:  # a device fault must never end the daemon
                self.stats.connected = False
                self.stats.error("disconnected", f"{type(exc).__name__}: {exc}")
                self._stop.wait(self.retry_s)

    def _run(self) -> bool | None:  # pragma: no cover - abstract
        """One connected session; return False when the source is exhausted for good."""
        raise NotImplementedError


class CameraSource(ThreadedSource):
    """Base of camera sources: ``camera`` (intrinsics and pose), frames into ``output``."""

    name = "camera"
    camera: Camera
    #: The data's layout ("sim", "punyo", "rosbag", "realsense", ...): with the configuration's
    #: ``profile = "auto"`` it picks the sensor profile (bubble_rt.sensor.profile_for_layout).
    #: A simulated camera gives its scene's profile ("sim" or "punyo").
    layout: str = "sim"
    #: A replay of this project's recording (``recorded``): the live run's configuration TOML
    #: and fitted mesh, which the daemon then uses; empty / None for every other source.
    recorded_settings: str = ""
    recorded_mesh: Any = None
    #: ... and its re-zero steps (bubble_rt.daemon.rezero), applied instead of deciding.
    recorded_rezero: list[Any] | None = None

    def __init__(self, lossless: bool = False) -> None:
        super().__init__()
        self.output: Mailbox[Frame] = Mailbox(STAGE_FRAMES)
        #: When set, the pressure carried by each frame is pushed here ("camera" pressure).
        self.pressure_out: PressureBuffer | None = None
        self.lossless = lossless
        self._count = 0

    def prepare(self) -> None:
        """Open enough to know ``camera``; raises :class:`SourceError` with a clear message."""

    def reference_frames(self, n: int) -> list[Frame] | None:
        """Frames of the untouched membrane if the source knows them (sim, recordings)."""
        return None

    def emit(self, frame: Frame) -> None:
        self.stats.received += 1
        self.stats.connected = True
        self.stats.last_time = frame.t
        if (
            self.pressure_out is not None
            and frame.meta.get("has_pressure", True)
            and math.isfinite(frame.pressure_pa)
        ):
            self.pressure_out.push(frame.t, frame.pressure_pa)
        self.output.put(frame, block=self.lossless, stop=self._stop)

    def _stamp(self, frame: Frame) -> Frame:
        """Restamp a stored/simulated frame with the daemon clock, keep its own time in meta."""
        meta = dict(frame.meta)
        meta.setdefault("source_t", frame.t)
        meta.setdefault("source_index", frame.index)
        idx = frame.index if getattr(self, "keep_index", False) else self._count
        self._count += 1
        now = time.time()
        return replace(frame, t=now, t_pressure=now, index=idx, meta=meta)


class IterableCamera(CameraSource):
    """Frames from a re-iterable factory, paced at ``rate_hz`` or by their own timestamps."""

    name = "iterable"

    def __init__(
        self,
        frames: Callable[[], Iterator[Frame]],
        camera: Camera,
        rate_hz: float | None = 30.0,
        loop: bool = True,
        lossless: bool = False,
        by_timestamps: bool = False,
        reference: Callable[[int], list[Frame] | None] | None = None,
        keep_index: bool = False,
    ) -> None:
        super().__init__(lossless=lossless)
        #: Keep the frames' own indices (a single pass over a recording) instead of renumbering.
        self.keep_index = keep_index
        self._frames = frames
        self.camera = camera
        #: Start the frames over after an error (a device reconnecting); finite sources
        #: (replays) end instead.
        self.restart_on_error = True
        #: Check each frame against ``camera`` (shape, dtype, valid depth) and skip bad ones.
        self.camera_check = False
        #: Bad frames skipped, named (file and index) with the reason; the last 100.
        self.bad_frames: deque[str] = deque(maxlen=100)
        #: Skipped frames and readings counted per kind (colour, depth, pressure, frame).
        self.skipped = FaultTally(keep=100)
        self.rate_hz = rate_hz
        self.loop = loop
        self.by_timestamps = by_timestamps
        self._reference = reference
        #: When the next frame is due after a pass (looping): the loop keeps the camera's
        #: period, as a real camera would (restarting the pace there emitted the first frame of
        #: a pass right after the last one, which then replaced it unprocessed).
        self._next_due: float | None = None

    def reference_frames(self, n: int) -> list[Frame] | None:
        """The source's reference frames, restamped with the daemon clock like every frame."""
        frames = None if self._reference is None else self._reference(n)
        return None if frames is None else restamp_reference(frames)

    def _main(self) -> None:
        if self.restart_on_error:
            super()._main()
            return
        try:  # a finite source (replay) never starts over after an error
            while not self._stop.is_set() and self._run() is not False:
                pass
        except Exception as exc:
            self.stats.connected = False
            self.stats.error("failed", f"{type(exc).__name__}: {exc}")
        self.finished.set()

    def _skip(self, fault: FrameFault) -> None:
        """Count and name a FrameFault: ``bad_reading`` for a pressure reading a bag's frames
        do without, else ``bad_frame``; ``skipped`` counts them per kind."""
        what = "reading" if fault.reading else "frame"
        self.stats.error(f"bad_{what}", f"skipped bad {what}: {fault}")
        self.bad_frames.append(str(fault))
        self.skipped.add(fault)
        log.warning("%s: skipped bad %s: %s", self.name, what, fault)

    def _run(self) -> bool | None:
        next_t, self._next_due = self._next_due or time.monotonic(), None
        prev_src_t: float | None = None
        good = 0
        for frame in self._frames():
            if self._stop.is_set():
                return False
            if not isinstance(frame, Frame):  # a FrameFault: skipped, counted and named
                self._skip(frame)
                continue
            if self.camera_check:
                try:
                    frame.validate(self.camera, need_images=True)
                except Exception as exc:
                    where = f"{frame.meta.get('source', self.name)} frame {frame.index}"
                    self._skip(fault_of(exc, frame.index, where))
                    continue
            good += 1
            if self.rate_hz:
                period = 1.0 / self.rate_hz
                if self.by_timestamps and prev_src_t is not None:
                    period = min(max(frame.t - prev_src_t, 0.0), 1.0)
                prev_src_t = frame.t
                delay = next_t - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return False
                # Do not try to catch up after a hiccup: pace from now.
                next_t = max(next_t, time.monotonic() - period) + period
            self.emit(self._stamp(frame))
        if self.rate_hz:
            self._next_due = next_t
        if good == 0 and not self._stop.is_set():
            # A pass without one usable frame would loop forever without output.
            self.stats.connected = False
            self.stats.error(
                "no_frame",
                f"no usable frame in a whole pass ({self.skipped.summary() or 'no frame at all'})",
            )
            log.error("%s: no usable frame in a whole pass: the source ends", self.name)
            return False
        return None if self.loop else False


def restamp_reference(frames: list[Frame]) -> list[Frame]:
    """Reference frames on the daemon clock (``time.time()``), their own time kept in meta.

    Simulated reference frames carry negative scene times (they precede frame 0) and
    recorded ones their recording's times: the daemon and its recordings use one clock.
    """
    now = time.time()
    n = len(frames)
    out = []
    for i, f in enumerate(frames):
        meta = dict(f.meta)
        meta.setdefault("source_t", f.t)
        t = now - (n - 1 - i) * 1e-3
        out.append(replace(f, t=t, t_pressure=t, meta=meta))
    return out


class ReplayCamera(IterableCamera):
    """A recording: this project's MCAP files, the punyo layout or a ROS 2 bag
    (``recordings``; ``bag_options`` go to the bag reader). Paced by the frames' timestamps.

    A frame that cannot be read (truncated or garbage file, wrong shape or dtype, no valid
    depth, NaN pressure) is skipped, counted (``stats.errors["bad_frame"]``) and named in
    ``stats.last_error``; the replay goes on to the end and, unless ``loop``, stops there: it
    never starts over after an error. What a damaged MCAP file lost is in
    ``stats.errors["recording"]`` / ``recording_report``. A file that is not a readable
    recording is refused at once (:class:`SourceError` with the reason).

    ``recorded`` (this project's MCAP): replay what the live run solved, with what it
    depended on: only the frames it published forces for, and ``recorded_settings`` (the
    daemon's configuration TOML) and ``recorded_mesh`` (the fitted mesh) for the daemon to use.
    """

    #: What a damaged MCAP file lost (``bubble_rt.io.mcap_scan.ReadReport``), else None.
    recording_report: Any = None

    def __init__(
        self,
        path: str,
        realtime: bool = True,
        loop: bool = False,
        recorded: bool = False,
        **bag_options: Any,
    ) -> None:
        from pathlib import Path

        p = Path(path)
        rec, reference, report = _open_replay(p, bag_options)
        published: set[int] = getattr(rec, "published", set()) if recorded else set()

        def frames() -> Iterator[Any]:
            # Every layout names the frames it skips (FrameFault); a bag also the pressure
            # readings it skipped, once per pass.
            yield from getattr(rec, "reading_faults", [])
            out = rec.frames(faults=True)
            if published:  # the frames the live run solved, as it solved them
                out = (f for f in out if not isinstance(f, Frame) or f.index in published)
            yield from out

        super().__init__(
            frames,
            rec.camera,
            rate_hz=30.0 if realtime else None,
            loop=loop,
            lossless=not realtime,
            by_timestamps=True,
            reference=reference,
            keep_index=not loop,
        )
        self.name = f"replay:{p.name}"
        self.stats.name = self.name
        self.restart_on_error = False
        # Frames are checked against the recording's camera when the file states it.
        self.camera_check = getattr(rec, "has_camera_info", True)
        self.layout = getattr(rec, "layout", "sim")
        self.recording_report = report
        if recorded:
            self.recorded_settings = getattr(rec, "settings_toml", "")
            self.recorded_mesh = getattr(rec, "mesh", None)
            self.recorded_rezero = list(getattr(rec, "rezero", []))
        self._report_losses(rec, report)

    def _report_losses(self, rec: Any, report: Any) -> None:
        """What a cut or damaged recording lost, in the source's status and the log."""
        if getattr(rec, "lost", ""):  # a cut or damaged bag
            self.stats.error("recording", rec.lost)
            log.warning("replay: %s", rec.lost)
        if report is not None and not report.complete:
            text = report.summary()
            if getattr(rec, "frames_indexed", None) is not None and len(rec) < rec.frames_indexed:
                text += f"; {len(rec)} of {rec.frames_indexed} frames readable"
            self.stats.error("recording", text)
            log.warning("replay: %s", text)


def _open_replay(
    p: Any, bag_options: dict[str, Any]
) -> tuple[Any, Callable[[int], list[Frame] | None] | None, Any]:
    """The recording at ``p``, its reference frames (an MCAP file that has them) and its read
    report (MCAP); SourceError when it cannot be read or holds no frame to replay."""
    import warnings

    from bubble_rt.io.rosbag import is_rosbag

    if not p.exists():
        raise SourceError(f"replay: no such recording {str(p)!r}")
    reference: Callable[[int], list[Frame] | None] | None = None
    report: Any = None
    try:
        if p.suffix == ".mcap" and not is_rosbag(p):
            from bubble_rt.io.mcap import McapRecording

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rec: Any = McapRecording(p)
            report = rec.report
            if rec.has_reference:
                reference = rec.reference_frames
        else:
            from bubble_rt.io.recordings import open_recording

            rec = open_recording(p, **bag_options)
    except Exception as exc:
        raise SourceError(f"replay: cannot read {p}: {exc}") from exc
    if len(rec) == 0:  # e.g. an MCAP file cut after its reference frames: nothing to replay
        lost = f" ({report.summary()})" if report is not None else ""
        raise SourceError(f"replay: {p}: no frame to replay after the reference{lost}")
    if getattr(rec, "topics_note", ""):
        log.info("replay: %s", rec.topics_note)
    return rec, reference, report
