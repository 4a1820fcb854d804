"""Capture sources for the daemon: one thread each, feeding bounded latest-value slots.

Camera sources (:class:`SimCamera`, :class:`ReplayCamera`, :class:`RealSenseCamera`) put
:class:`~bubble_rt.frames.Frame` objects into a :class:`LatestSlot` (one item: a newer frame
replaces an unconsumed older one, which is counted as dropped). Pressure sources
(:class:`SerialPressure`, :class:`ConstantPressure`, or the pressure carried by sim/replay
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
import re
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
class LatestSlot(Generic[T]):
    """A one-item mailbox: ``put`` replaces an unconsumed item (counted in ``dropped``).

    With ``put(block=True)`` the producer waits instead until the consumer took the previous
    item (lossless replay). Never grows: the daemon always works on the newest data.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._has = False
        self._closed = False
        self.put_count = 0
        self.dropped = 0

    def put(self, item: T, block: bool = False, stop: threading.Event | None = None) -> bool:
        """Store ``item``; returns False if an older item was dropped (or the slot closed)."""
        with self._cond:
            if block:
                while self._has and not self._closed and not (stop is not None and stop.is_set()):
                    self._cond.wait(0.05)
            if self._closed:
                return False
            dropped = self._has
            if dropped:
                self.dropped += 1
            self._item, self._has = item, True
            self.put_count += 1
            self._cond.notify_all()
            return not dropped

    def get(self, timeout: float) -> T | None:
        """Take the item, waiting up to ``timeout`` seconds; None when nothing arrived."""
        with self._cond:
            if not self._has:
                self._cond.wait_for(lambda: self._has or self._closed, timeout)
            if not self._has:
                return None
            item, self._item, self._has = self._item, None, False
            self._cond.notify_all()
            return item

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

    def __init__(self, lossless: bool = False) -> None:
        super().__init__()
        self.output: LatestSlot[Frame] = LatestSlot()
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
        next_t = time.monotonic()
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


class SimCameraSource(IterableCamera):
    """An :class:`IterableCamera` whose frames a :class:`~bubble_rt.daemon.sim_producer.
    SimProducer` renders in its own process; ``stop`` ends that process too."""

    producer: Any

    #: One rendered pass read from the disk cache (then nothing is rendered), or None.
    cached_pass: list[Any] | None = None

    def prepare(self) -> None:
        """Start the renderer process now, so it loads while the daemon sets up (with a cached
        pass it renders nothing: it loads the physics, then derives the true contact)."""
        self.producer.start()
        if self.cached_pass is not None:  # the physics is cached too: load it meanwhile
            threading.Thread(
                target=self.producer.preload_truth, name="sim-truth-preload", daemon=True
            ).start()

    def stop(self, timeout: float = 1.0) -> None:
        super().stop(timeout)
        self.producer.stop(timeout)


def SimCamera(
    scene: str = "demo",
    rate_hz: float | None = None,
    loop: bool = True,
    lossless: bool = False,
    prerender: bool = True,
    simulator: str | None = None,
) -> SimCameraSource:
    """The simulator (``bubble_rt.sim``) on a scene, looped, paced at the scene's camera rate.

    The frames are rendered in a separate process (:mod:`bubble_rt.daemon.sim_producer`), so
    the simulated camera takes no time from the estimation threads, like a real camera; they
    carry the simulator's ground truth (``Frame.truth``). Frame indices keep counting across
    loops (``index = pass * scene.frames + i``), so frame ``k`` shows scene frame
    ``k % scene.frames``. With ``prerender`` the first pass is kept in memory and later passes
    replay it (the renderer process is then idle); it is also stored in the disk cache
    (``sim_producer.pass_cache_path``, keyed by the scene and the simulator's code), and later
    runs replay it from there from their first frame, rendering nothing. ``simulator``: the simulator class as
    ``module:attribute`` (default ``bubble_rt.sim:Simulator``; tests name a fake).
    """
    from bubble_rt.daemon import sim_producer as sp

    path = simulator or sp.DEFAULT_SIMULATOR
    try:
        sim = sp.load_simulator_class(path)(scene)  # the scene and camera; no physics yet
    except Exception as exc:
        raise SourceError(f"cannot load simulator scene {scene!r}: {exc}") from exc
    n_frames = int(sim.scene.frames)
    producer = sp.SimProducer(
        scene, sim, repeat=loop and not prerender, keep_pass=prerender, simulator=path
    )
    # With prerender, a pass rendered by an earlier run is read from the disk cache.
    pass_path = sp.pass_cache_path(sim) if prerender else None
    stored = None if pass_path is None else sp.load_pass(pass_path)
    cache: list[Frame] = []
    state = {"pass": 0, "complete": False}
    src: SimCameraSource

    def frames() -> Iterator[Frame]:
        k = state["pass"]
        state["pass"] += 1
        offset = k * n_frames
        if stored is not None:
            for fields, arrays in stored:
                f = producer.frame_of(fields, arrays)
                yield replace(f, index=f.index + offset)
            return
        if state["complete"]:
            for f in cache:
                yield replace(f, index=f.index + offset)
            return
        cache.clear()
        for f in producer.frames(src._stop):
            if prerender:
                cache.append(f)
            yield replace(f, index=f.index + offset)
        state["complete"] = prerender
        if prerender and pass_path is not None:  # the next runs read it from disk
            threading.Thread(
                target=sp.store_pass,
                args=(pass_path, list(cache)),
                name="sim-pass-cache",
                daemon=True,
            ).start()

    def reference(n: int) -> list[Frame] | None:
        return producer.reference_frames(n, src._stop)

    hz = rate_hz or float(sim.scene.rates.camera_hz)
    src = SimCameraSource(
        frames,
        sim.camera,
        rate_hz=None if lossless else hz,
        loop=loop,
        lossless=lossless,
        reference=reference,
        keep_index=True,
    )
    src.producer = producer
    src.cached_pass = stored
    # Paced by the estimator (every frame processed): a frame waits for its true contact.
    producer.wait_for_truth = lossless
    src.name = f"sim:{scene}"
    src.stats.name = src.name
    return src


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


def ReplayCamera(
    path: str,
    realtime: bool = True,
    loop: bool = False,
    recorded: bool = False,
    **bag_options: Any,
) -> IterableCamera:
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
    import warnings
    from pathlib import Path

    from bubble_rt.io.rosbag import is_rosbag

    p = Path(path)
    if not p.exists():
        raise SourceError(f"replay: no such recording {path!r}")
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
        raise SourceError(f"replay: cannot read {path}: {exc}") from exc
    if len(rec) == 0:  # e.g. an MCAP file cut after its reference frames: nothing to replay
        lost = f" ({report.summary()})" if report is not None else ""
        raise SourceError(f"replay: {path}: no frame to replay after the reference{lost}")
    if getattr(rec, "topics_note", ""):
        log.info("replay: %s", rec.topics_note)

    published: set[int] = getattr(rec, "published", set()) if recorded else set()

    def frames() -> Iterator[Any]:
        # Every layout names the frames it skips (FrameFault); a bag also the pressure
        # readings it skipped, once per pass.
        yield from getattr(rec, "reading_faults", [])
        out = rec.frames(faults=True)
        if published:  # the frames the live run solved, as it solved them
            out = (f for f in out if not isinstance(f, Frame) or f.index in published)
        yield from out

    src = IterableCamera(
        frames,
        rec.camera,
        rate_hz=30.0 if realtime else None,
        loop=loop,
        lossless=not realtime,
        by_timestamps=True,
        reference=reference,
        keep_index=not loop,
    )
    src.name = f"replay:{p.name}"
    src.stats.name = src.name
    src.restart_on_error = False
    # Frames are checked against the recording's camera when the file states it.
    src.camera_check = getattr(rec, "has_camera_info", True)
    src.layout = getattr(rec, "layout", "sim")  # type: ignore[attr-defined]
    src.recording_report = report  # type: ignore[attr-defined]
    src.recorded_settings = getattr(rec, "settings_toml", "") if recorded else ""  # type: ignore[attr-defined]
    src.recorded_mesh = getattr(rec, "mesh", None) if recorded else None  # type: ignore[attr-defined]
    if getattr(rec, "lost", ""):  # a cut or damaged bag: what was lost
        src.stats.error("recording", rec.lost)
        log.warning("replay: %s", rec.lost)
    if report is not None and not report.complete:
        text = report.summary()
        if getattr(rec, "frames_indexed", None) is not None and len(rec) < rec.frames_indexed:
            text += f"; {len(rec)} of {rec.frames_indexed} frames readable"
        src.stats.error("recording", text)
        log.warning("replay: %s", text)
    return src


class RealSenseCamera(CameraSource):
    """Intel RealSense (D405) through pyrealsense2: colour + depth aligned to colour.

    Stalls (no frame within ``timeout_ms``) are counted; after ``max_stalls`` in a row the
    pipeline is restarted (unplug / replug recovers by itself).
    """

    name = "realsense"
    layout = "realsense"  # Punyo hardware: bubble_rt.sensor picks the Punyo profile
    retry_s = 1.0

    def __init__(
        self,
        serial: str = "",
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        timeout_ms: int = 1000,
        max_stalls: int = 3,
        rs_module: Any = None,
    ) -> None:
        super().__init__()
        self.serial = serial
        self.width, self.height, self.fps = width, height, fps
        self.timeout_ms = timeout_ms
        self.max_stalls = max_stalls
        self._rs = rs_module
        self._pipe: Any = None
        self._depth_scale = 0.0

    def _module(self) -> Any:
        if self._rs is None:
            try:
                import pyrealsense2 as rs
            except ImportError:
                raise SourceError(
                    "camera source 'realsense' needs pyrealsense2, which is not installed: "
                    "pip install 'bubble_rt[realsense]' (or pip install pyrealsense2)"
                ) from None
            self._rs = rs
        return self._rs

    def _open(self) -> None:
        rs = self._module()
        devices = list(rs.context().query_devices())
        if not devices:
            raise SourceError(
                "no RealSense device found: check the USB 3 cable and that no other program "
                "holds the camera (realsense-viewer)"
            )
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, self.fps)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipe = rs.pipeline()
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise SourceError(f"cannot start the RealSense streams: {exc}") from exc
        self._depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        coeffs = tuple(float(c) for c in list(intr.coeffs)[:5])
        self.camera = Camera(
            fx=float(intr.fx),
            fy=float(intr.fy),
            cx=float(intr.ppx),
            cy=float(intr.ppy),
            width=int(intr.width),
            height=int(intr.height),
            distortion=coeffs + (0.0,) * (5 - len(coeffs)),  # type: ignore[arg-type]
        )
        self._align = rs.align(rs.stream.color)
        self._pipe = pipe

    def _close(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except Exception:
                pass
            self._pipe = None

    def prepare(self) -> None:
        self._open()

    def _run(self) -> bool | None:
        if self._pipe is None:
            self._open()
        stalls = 0
        try:
            while not self._stop.is_set():
                try:
                    frames = self._pipe.wait_for_frames(self.timeout_ms)
                except RuntimeError as exc:
                    stalls += 1
                    self.stats.error("stall", f"no frame within {self.timeout_ms} ms: {exc}")
                    if stalls >= self.max_stalls:
                        raise SourceError(f"camera lost after {stalls} stalls") from exc
                    continue
                stalls = 0
                t = time.time()
                aligned = self._align.process(frames)
                color = aligned.get_color_frame()
                depth = aligned.get_depth_frame()
                if not color or not depth:
                    self.stats.error("incomplete", "frame set without colour or depth")
                    continue
                rgb = np.array(np.asanyarray(color.get_data()), dtype=np.uint8, copy=True)
                z = np.asanyarray(depth.get_data()).astype(np.float32) * self._depth_scale
                idx = self._count
                self._count += 1
                try:
                    # The camera has no pressure: the daemon pairs one from the pressure source.
                    frame = Frame(
                        rgb=rgb,
                        depth=z,
                        pressure_pa=0.0,
                        t=t,
                        index=idx,
                        meta={
                            "device_time_ms": float(frames.get_timestamp()),
                            "has_pressure": False,
                        },
                    )
                except ValueError as exc:  # e.g. no valid depth pixel (lens covered)
                    self.stats.error("bad_frame", str(exc))
                    continue
                self.emit(frame)
        finally:
            self._close()
        return None

    def stop(self, timeout: float = 1.0) -> None:
        super().stop(timeout)
        self._close()


# ------------------------------------------------------------------------------ serial
_LINE = re.compile(
    r"^\s*(?P<value>[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*(?P<unit>hPa|Pa|mbar)?"
    r"(\s+t\s*=\s*(?P<t>[-+]?\d+(\.\d*)?))?\s*$"
)


class LineError(ValueError):
    """A serial line that is not a valid reading; ``kind`` classifies it for the counters."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind


def parse_pressure_line(
    raw: bytes, default_unit: str = "hPa", min_pa: float = 30000.0, max_pa: float = 200000.0
) -> tuple[float, float | None] | None:
    """Parse one line of the serial protocol: ``<value> [hPa|Pa|mbar] [t=<sensor ms>]``.

    Returns (pascals, sensor time ms or None), or None for a blank line or a ``#`` comment.
    Raises :class:`LineError` with kind "garbage" (not text), "non_numeric" or "out_of_range".
    """
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise LineError("garbage", f"not ASCII text: {raw[:32]!r}") from None
    if not text or text.startswith("#"):
        return None
    if any(not c.isprintable() for c in text):
        raise LineError("garbage", f"control characters in line: {text[:32]!r}")
    m = _LINE.match(text)
    if m is None:
        raise LineError("non_numeric", f"not a reading: {text[:40]!r}")
    value = float(m.group("value"))
    unit = m.group("unit") or default_unit
    pa = value if unit == "Pa" else value * HPA
    if not (math.isfinite(pa) and min_pa <= pa <= max_pa):
        raise LineError("out_of_range", f"{pa:.0f} Pa outside [{min_pa:.0f}, {max_pa:.0f}] Pa")
    t = m.group("t")
    return pa, (float(t) if t is not None else None)


class SerialPressure(ThreadedSource):
    """Pressure readings from a serial port (pyserial), one per line, into ``buffer``.

    Faults are counted in ``stats.errors`` by kind: garbage, non_numeric, out_of_range,
    partial (a line cut at (re)connection or longer than ``max_line`` bytes) and port
    (the port vanished; it is reopened every ``reconnect_s``).
    """

    name = "serial"
    max_line = 128

    def __init__(
        self,
        port: str,
        buffer: PressureBuffer,
        baud: int = 115200,
        default_unit: str = "hPa",
        min_pa: float = 30000.0,
        max_pa: float = 200000.0,
        reconnect_s: float = 0.5,
    ) -> None:
        super().__init__()
        self.port = port
        self.buffer = buffer
        self.baud = baud
        self.default_unit = default_unit
        self.min_pa, self.max_pa = min_pa, max_pa
        self.retry_s = reconnect_s
        self.name = f"serial:{port}"
        self.stats.name = self.name
        self.last_sensor_ms: float | None = None

    def _main(self) -> None:
        while not self._stop.is_set():
            try:
                self._run()
            except Exception as exc:
                self.stats.connected = False
                self.stats.error("port", f"serial port {self.port}: {type(exc).__name__}: {exc}")
                self._stop.wait(self.retry_s)

    def _run(self) -> bool | None:
        import serial

        with serial.serial_for_url(self.port, baudrate=self.baud, timeout=0.05) as ser:
            self.stats.connected = True
            pending = b""
            # The first line after opening is usually cut: we joined the stream mid-line.
            first = True
            while not self._stop.is_set():
                chunk = ser.read(ser.in_waiting or 1)
                if not chunk:
                    continue
                pending += chunk
                *lines, pending = pending.split(b"\n")
                for line in lines:
                    if first:
                        first = False
                        if line.strip():
                            self.stats.error("partial", f"discarded first line {line[:32]!r}")
                        continue
                    if len(line) > self.max_line:
                        self.stats.error("partial", f"line longer than {self.max_line} bytes")
                        continue
                    self._handle(line)
                if len(pending) > self.max_line:
                    self.stats.error("partial", f"line longer than {self.max_line} bytes")
                    pending = b""
                    first = True  # resynchronise at the next newline
        return None

    def _handle(self, line: bytes) -> None:
        try:
            got = parse_pressure_line(line, self.default_unit, self.min_pa, self.max_pa)
        except LineError as exc:
            self.stats.error(exc.kind, str(exc))
            return
        if got is None:
            return
        pa, sensor_ms = got
        now = time.time()
        self.last_sensor_ms = sensor_ms
        self.stats.received += 1
        self.stats.last_time = now
        self.buffer.push(now, pa)


# ------------------------------------------------------------------------------ factory
def make_camera_source(cfg: Any) -> CameraSource:
    """Camera source from a :class:`~bubble_rt.config.CameraConfig`."""
    from bubble_rt.config import split_source

    kind, arg = split_source(cfg.source)
    if kind == "sim":
        return SimCamera(
            arg or "demo", loop=cfg.loop, lossless=cfg.pace == "fast", prerender=cfg.sim_prerender
        )
    if kind == "replay":
        return ReplayCamera(
            arg,
            realtime=cfg.pace == "realtime",
            loop=cfg.loop,
            recorded=cfg.replay_settings == "recorded",
        )
    if kind == "realsense":
        return RealSenseCamera(arg, cfg.width, cfg.height, cfg.fps)
    raise SourceError(f"unknown camera source {cfg.source!r}")


def make_pressure_source(
    cfg: Any, camera: CameraSource
) -> tuple[PressureBuffer, ThreadedSource | None]:
    """(buffer the daemon interpolates, thread feeding it or None) from a PressureConfig."""
    from bubble_rt.config import split_source

    kind, arg = split_source(cfg.source)
    if kind == "constant":
        return ConstantPressure(float(arg)), None
    buf = PressureBuffer(cfg.buffer)
    if kind == "camera":
        camera.pressure_out = buf
        return buf, None
    if kind == "serial":
        return buf, SerialPressure(
            arg, buf, cfg.baud, cfg.default_unit, cfg.min_pa, cfg.max_pa, cfg.reconnect_s
        )
    raise SourceError(f"unknown pressure source {cfg.source!r}")
