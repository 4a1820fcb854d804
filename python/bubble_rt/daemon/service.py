"""The streaming daemon: sensor frames in, force and contact frames out over ZeroMQ.

Threads (all daemon threads, all loops bounded by timeouts so shutdown takes < 2 s):

* capture: one per source (``bubble_rt.daemon.sources``), feeding a two-frame mailbox
  (camera) or a pressure ring buffer;
* stage 1: the next camera frame, with the pressure at its capture time: the reference
  (first K frames, and on ``tare``), then the deformation (flow + lifting, C++, no GIL);
* stage 2: the forces (C++ ADMM, no GIL), contact patches, the published ForceFrame, so the
  flow of frame k+1 overlaps the solve of frame k;
* control: ControlRequests on a ROUTER socket (``bubble_rt.daemon.control``), and the Status
  published periodically (``bubble_rt.daemon.health``).

A frame that arrives while a stage is busy waits behind at most one other
(``sources.STAGE_FRAMES``): one slow frame delays the next instead of losing it. A frame that
finds the stage's mailbox full replaces the oldest waiting one (counted as a drop), so the
latency stays bounded when a stage cannot keep up.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import zmq

from bubble_rt.camera import Camera
from bubble_rt.config import DaemonConfig, EstimatorSection
from bubble_rt.daemon import control, faults, health, rezero, startup
from bubble_rt.daemon.processor import (
    EstimatorProcessor,
    PatchFinder,
    Processor,
    ProcessorFactory,
)
from bubble_rt.daemon.sim_truth import attach_sim_truth
from bubble_rt.daemon.source_config import make_camera_source, make_pressure_source
from bubble_rt.daemon.sources import (
    STAGE_FRAMES,
    CameraSource,
    Mailbox,
    PressureBuffer,
    ThreadedSource,
    pair_pressure,
)
from bubble_rt.frames import Frame
from bubble_rt.io import protocol
from bubble_rt.io.mcap import TOPIC_MESH

#: Largest message the control socket accepts at the transport level (ZMQ_MAXMSGSIZE; bigger:
#: ZeroMQ drops the connection, see ``protocol.MAX_MESSAGE_BYTES``).
CONTROL_MAX_TRANSPORT_BYTES = protocol.MAX_MESSAGE_BYTES
#: Shortest time (s) between two status messages that differ only in their reason.
REASON_REFRESH_S = 0.1


# ------------------------------------------------------------------------ daemon
@dataclass
class _Item:
    frame: Frame
    reasons: list[str]
    data: Any
    timings: dict[str, float] = field(default_factory=dict)
    t_stage1_end: float = 0.0
    #: Solve this frame from a cold start (first frame of a recording).
    cold: bool = False
    #: The recorder that got this frame's input: only it gets the forces (so a replay does).
    recorder: Any = None
    #: The frame's node displacements from the tare's mesh (N x 3, m; re-zeroing evidence).
    displacements: Any = None


#: A fault kind is logged at most once per this many seconds (with its count so far).
ERROR_LOG_PERIOD_S = 10.0
log = logging.getLogger("bubble_rt.daemon")


class DaemonError(RuntimeError):
    """The daemon cannot start (socket in use, source missing, ...)."""


class Daemon:
    """Runs the whole pipeline; ``start()`` then ``stop()`` (or use as a context manager).

    Sources and the processor can be injected (tests, embedding); by default they are built
    from ``config``.
    """

    def __init__(
        self,
        config: DaemonConfig | None = None,
        *,
        camera: CameraSource | None = None,
        pressure: tuple[PressureBuffer, ThreadedSource | None] | None = None,
        processor_factory: ProcessorFactory | None = None,
    ) -> None:
        self.config = config or DaemonConfig()
        self._camera_src = camera
        self._pressure_arg = pressure
        self._factory: ProcessorFactory = processor_factory or EstimatorProcessor
        self.sensor_id = self.config.sensor_id
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._pub_lock = threading.Lock()
        self._proc_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._status_lock = threading.Lock()
        self.processor: Processor | None = None
        self.mesh_msg: Any | None = None
        self._patches: PatchFinder | None = None
        self._mid: Mailbox[_Item] = Mailbox(STAGE_FRAMES)
        self._pending_params: dict[str, float] = {}
        self._tare_requested = False
        self._ref_frames: list[Frame] = []
        self._collecting: list[Frame] = []
        self.recorder: Any = None
        #: The fitted mesh of a replayed recording (used instead of fitting again).
        self._recorded_mesh: Any = None
        #: Recording just started: its first solved frame starts the solver cold, so the
        #: recording alone determines its forces (a replay reproduces them).
        self._cold_next = False
        #: Extra outputs, e.g. bubble_rt.daemon.foxglove_view.FoxgloveView: on_frame(frame,
        #: force msg, mesh msg, recorder), on_status(msg, recorder), close().
        self.viewers: list[Any] = []
        self.seq = 0
        self.frames_published = 0
        self.errors: dict[str, int] = {}
        self._error_logged: dict[str, float] = {}
        self.last_error = ""
        self.last_error_time = 0.0
        #: What the threads record for the daemon's health and status (health.Vitals).
        self.vitals = health.Vitals()
        self._last_state: tuple[int, str] | None = None
        self.ctx: zmq.Context | None = None
        #: Following the drift while untouched (bubble_rt.daemon.rezero).
        self.rezero = rezero.Rezeroing(self.config.auto_zero, self.report_error)

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> Daemon:
        cfg = self.config
        self.vitals.started_at = time.time()
        if cfg.processing.opencv_threads > 0:
            from bubble_rt import _core

            _core._set_opencv_threads(cfg.processing.opencv_threads)
        problem = startup.mesh_file_problem(self.config)
        if problem:
            raise DaemonError(problem)
        if self._camera_src is None:
            self._camera_src = make_camera_source(cfg.camera)
        cam = self._camera_src
        self.config, self._recorded_mesh = startup.recorded_settings(self.config, cam)
        self.rezero.use_recording(cam.recorded_rezero)
        self.config = startup.resolve_profile(self.config, cam.layout)
        cfg = self.config
        if self._pressure_arg is None:
            self._pressure_arg = make_pressure_source(cfg.pressure, cam)
        self.pressure_buffer, self._pressure_src = self._pressure_arg
        cam.prepare()
        self.camera: Camera = cam.camera
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.PUB)
        self.pub.setsockopt(zmq.SNDHWM, cfg.network.sndhwm)
        self.pub.setsockopt(zmq.LINGER, 0)
        self.ctl = self.ctx.socket(zmq.ROUTER)
        self.ctl.setsockopt(zmq.LINGER, 0)
        self.ctl.setsockopt(zmq.MAXMSGSIZE, CONTROL_MAX_TRANSPORT_BYTES)
        for sock, addr, what in (
            (self.pub, cfg.network.pub, "network.pub"),
            (self.ctl, cfg.network.control, "network.control"),
        ):
            try:
                sock.bind(addr)
            except zmq.ZMQError as exc:
                self._close_sockets()
                raise DaemonError(f"cannot bind {what} {addr}: {exc}") from exc
        self.pub_address = str(self.pub.getsockopt_string(zmq.LAST_ENDPOINT))
        self.control_address = str(self.ctl.getsockopt_string(zmq.LAST_ENDPOINT))
        if cfg.recording.path:
            try:
                self.start_recording(cfg.recording.path, cfg.recording.overwrite)
            except ValueError as exc:
                self._close_sockets()
                raise DaemonError(f"recording.path: cannot record: {exc}") from exc
        cam.start()
        if self._pressure_src is not None:
            self._pressure_src.start()
        self._spawn(self._stage1_loop, "stage1")
        if cfg.processing.pipeline == "two_stage":
            self._spawn(self._stage2_loop, "stage2")
        self._spawn(self._control_loop, "control")
        return self

    def _spawn(self, target: Callable[[], None], name: str) -> None:
        th = threading.Thread(target=target, name=name, daemon=True)
        th.start()
        self._threads.append(th)

    def stop(self, timeout: float | None = None) -> None:
        """Stop threads, publish a final STOPPED status, finalise any recording."""
        if self._stop.is_set():
            return
        timeout = self.config.shutdown_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + 0.8 * timeout
        self._stop.set()
        self._mid.close()
        if self._camera_src is not None:
            self._camera_src.output.close()
        sources = [self._camera_src] + ([self._pressure_arg[1]] if self._pressure_arg else [])
        for src in sources:
            if src is not None:
                src.stop(0.0)  # signal first: they all wind down at once
        # Join every thread (capture ones too: a frame being rendered or tracked in C++ must
        # finish before the interpreter exits, else the C++ runtime aborts with
        # std::terminate).
        for src in sources:
            if src is not None:
                src.stop(max(0.0, deadline - time.monotonic()))
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))
        for viewer in self.viewers:
            viewer.close()
        if self.recorder is not None:
            rec, self.recorder = self.recorder, None
            rec.close(timeout=max(0.1, deadline - time.monotonic()))
        try:
            with self._pub_lock:
                self._send(protocol.status_topic(self.sensor_id), self.status_message(stopped=True))
            time.sleep(0.05)  # give the final status a moment on the wire (LINGER is 0)
        except Exception:
            pass
        self._close_sockets()
        if not self.alive_threads():
            # Release the extension's objects (estimator, tracker) only once no thread uses them.
            with self._proc_lock:
                self.processor = None
                self._patches = None

    def alive_threads(self) -> list[str]:
        """Names of the daemon's threads still running (after ``stop``: ones that did not end
        within the shutdown timeout, e.g. busy in native code)."""
        out = [th.name for th in self._threads if th.is_alive()]
        sources = [self._camera_src] + ([self._pressure_arg[1]] if self._pressure_arg else [])
        for src in sources:
            if src is not None and src.alive:
                out.append(f"src-{src.name}")
        return out

    def _close_sockets(self) -> None:
        for name in ("pub", "ctl"):
            s = getattr(self, name, None)
            if s is not None:
                s.close(linger=0)
        if self.ctx is not None:
            self.ctx.term()
            self.ctx = None

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    @property
    def ready(self) -> bool:
        return self.processor is not None

    def wait_ready(self, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not self._stop.is_set():
            if self.ready:
                return True
            time.sleep(0.02)
        return self.ready

    # ---------------------------------------------------------------- errors
    def report_error(self, kind: str, exc: BaseException | str) -> None:
        """Count a fault of ``kind`` (status: ``error_counts``, reason); logged once, then at
        most every ``ERROR_LOG_PERIOD_S`` per kind with the count: never a line per frame."""
        text = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
        now = time.time()
        with self._state_lock:
            n = self.errors[kind] = self.errors.get(kind, 0) + 1
            self.last_error = f"{kind}: {text}"
            self.last_error_time = now
            logged = self._error_logged.get(kind, 0.0)
            if now - logged >= ERROR_LOG_PERIOD_S:
                self._error_logged[kind] = now
                log.warning("%s error (%d so far): %s", kind, n, text)

    # ---------------------------------------------------------------- stage 1
    def _stage1_loop(self) -> None:
        cam = self._camera_src
        assert cam is not None
        cfg = self.config
        k = cfg.reference.frames
        try:
            given = cam.reference_frames(k)
        except Exception as exc:
            self.report_error("reference", exc)
            given = None
        if given and cam.pressure_out is not self.pressure_buffer:
            # Sim/recorded reference frames carry their own pressure: use the sensor's.
            paired = None
            while paired is None and not self._stop.is_set():
                paired = faults.reference_with_pressure(list(given), self.pressure_buffer.at)
                if paired is None:
                    self._stop.wait(0.05)
            given = paired
        if given:
            self._install_reference(list(given))
        two_stage = cfg.processing.pipeline == "two_stage"
        while not self._stop.is_set():
            frame = cam.output.get(timeout=cfg.processing.poll_s)
            if frame is None:
                continue
            t_take = time.time()
            self.vitals.last_frame_time = t_take
            try:
                frame, reasons = pair_pressure(
                    frame, self.pressure_buffer, cfg.pressure.stale_timeout_s
                )
            except Exception as exc:  # e.g. a pressure the frame refuses: count, never raise
                self.report_error("pressure", exc)
                continue
            if self.processor is None or self._tare_requested:
                self._collecting.append(frame)
                if len(self._collecting) >= k:
                    frames, self._collecting = self._collecting, []
                    self._install_reference(frames)
                continue
            cold = False
            recorder = self.recorder
            self.rezero.before(frame, self.processor, recorder)
            if recorder is not None:
                recorder.write_frame(frame)
                # Cleared by the solve that honours it (this frame may be dropped unsolved).
                cold = self._cold_next
            timings = {"wait": (t_take - frame.t) * 1e3}
            t0 = time.perf_counter()
            try:
                data = self.processor.stage1(frame)
            except Exception as exc:
                self.report_error("deformation", exc)
                continue
            timings["stage1"] = (time.perf_counter() - t0) * 1e3
            disp = self.rezero.displacements(data)
            item = _Item(frame, reasons, data, timings, time.perf_counter(), cold, recorder, disp)
            if two_stage:
                self._mid.put(item, block=cam.lossless, stop=self._stop)
            else:
                self._finish(item)

    def _install_reference(self, frames: list[Frame]) -> None:
        # Frames replaced meanwhile are no drops: no estimator could take them (before the
        # first reference, all of them).
        raw_before = health.raw_drops(self) if self.processor is not None else 0
        try:
            if self.processor is None:
                if self._recorded_mesh is not None and startup.takes_mesh(self._factory):
                    factory: Any = self._factory
                    proc = factory(self.config, self.camera, frames, mesh=self._recorded_mesh)
                else:
                    proc = self._factory(self.config, self.camera, frames)
                mesh = proc.mesh
                self._patches = PatchFinder(mesh)
                self.mesh_msg = protocol.encode_mesh(
                    self.sensor_id,
                    mesh.vertices,
                    mesh.triangles,
                    mesh.boundary,
                    self._patches.areas,
                )
                self.processor = proc
                if self.recorder is not None:
                    self.recorder.write_message(TOPIC_MESH, self.mesh_msg)
            else:
                with self._proc_lock:
                    self.processor.set_reference(frames)
            self._ref_frames = frames
            self.rezero.tare(self.processor, frames[-1].t)
            if self.recorder is not None:
                self.recorder.write_reference(frames)
            cam = self._camera_src
            if cam is not None and not cam.lossless:
                # Frames that waited while the estimator was built: the first force frame is
                # the newest one, not a backlog (not drops: counted out below).
                cam.output.keep_newest()
        except Exception as exc:
            self.report_error("reference", exc)
        finally:
            if self.processor is not None:
                self.vitals.drops_not_counted += health.raw_drops(self) - raw_before
            self._tare_requested = False

    def set_auto_zero(self, enabled: bool) -> None:
        """Turn re-zeroing on or off (control request ``set_auto_zero``)."""
        self.rezero.set_enabled(enabled)

    def request_tare(self) -> None:
        """Capture a new reference from the next untouched frames."""
        self._collecting = []
        self._tare_requested = True

    def queue_params(self, params: dict[str, float]) -> EstimatorSection:
        """Apply validated Params before the next solve; returns the new [estimator] section."""
        with self._state_lock:
            self._pending_params.update(params)
            est = replace(self.config.estimator, **params)  # type: ignore[arg-type]
            self.config = replace(self.config, estimator=est)
        return est

    # ---------------------------------------------------------------- stage 2
    def _stage2_loop(self) -> None:
        while not self._stop.is_set():
            item = self._mid.get(timeout=0.1)
            if item is not None:
                self._finish(item)

    def _finish(self, item: _Item) -> None:
        """Stage two of one frame: solve, then publish its force frame (and record it, and
        show it to the viewers)."""
        proc = self.processor
        if proc is None or self._patches is None or self.mesh_msg is None:
            return
        item.timings["queue"] = (time.perf_counter() - item.t_stage1_end) * 1e3
        t0 = time.perf_counter()
        try:
            est = self._solve(proc, item)
            reasons = self._reasons(item, est)
            self.rezero.observe(item.frame, est.contact, est.net_force, reasons, item.displacements)
            timings = {**item.timings, **{k: float(v) for k, v in est.timings_ms.items()}}
            timings["stage2"] = (time.perf_counter() - t0) * 1e3
            msg = self._force_message(proc, item, est, reasons, timings)
        except Exception as exc:
            self.report_error("estimator", exc)
            return
        self._publish(item, msg, reasons, est)

    def _solve(self, proc: Processor, item: _Item) -> Any:
        """The frame's Estimate, after the parameters queued since the last frame and, after a
        reference or a tare, a cold start."""
        with self._state_lock:
            params, self._pending_params = self._pending_params, {}
        with self._proc_lock:
            if params:
                proc.reconfigure(params)
            if item.cold and self._cold_next:
                self._cold_next = False
                proc.cold_start()
            return proc.stage2(item.frame, item.data)

    @staticmethod
    def _reasons(item: _Item, est: Any) -> list[str]:
        """Why the frame is degraded: the daemon's own reasons, the pipeline's plausibility
        checks (inputs and result), and the solver's or the forces' problems."""
        reasons = [*item.reasons, *est.degraded_reasons]
        for problem in (
            faults.solver_problem(est.info),
            faults.forces_problem(np.asarray(est.node_forces, np.float64), est.net_force),
        ):
            if problem:
                reasons.append(problem)
        return reasons

    def _force_message(
        self, proc: Processor, item: _Item, est: Any, reasons: list[str], timings: dict
    ) -> Any:
        """The ForceFrame of one estimate (``bubble_rt.v1``), with the simulator's truth when
        the frame is simulated."""
        assert self._patches is not None and self.mesh_msg is not None
        contact = np.asarray(est.contact, dtype=bool)
        forces = np.asarray(est.node_forces, dtype=np.float64)
        patches = self._patches.patches_of(est)
        msg = protocol.encode_force_frame(
            sensor_id=self.sensor_id,
            seq=self.seq,
            frame_index=item.frame.index,
            capture_time_ns=int(round(item.frame.t * 1e9)),
            mesh_id=self.mesh_msg.mesh_id,
            net_force=est.net_force,
            node_forces=forces,
            normal_pressure=est.normal_pressure,
            contact=contact,
            patches=patches,
            pressure_delta_pa=float(est.pressure_delta_pa),
            pressure_pa=float(item.frame.pressure_pa),
            timings_ms=timings,
            solver_info=est.info,
            valid_node_fraction=float(est.valid_node_fraction),
            degraded_reasons=reasons,
            net_torque=self._patches.net_torque_of(est),
            node_displacements=np.nan_to_num(np.asarray(est.displacements, dtype=np.float64)),
        )
        attach_sim_truth(msg, item.frame, proc.mesh)  # simulated sources only
        return msg

    def _publish(self, item: _Item, msg: Any, reasons: list[str], est: Any) -> None:
        """Stamp and send the frame; count it; record it and show it to the viewers."""
        now = time.time()
        protocol.stamp_publish(msg, time.time_ns())
        first = self.frames_published == 0
        self.frames_published += 1
        if first:  # "running" reaches subscribers before the first force frame, not after it
            self._send_status()
        with self._pub_lock:
            self._send(protocol.force_topic(self.sensor_id), msg)
        self.seq += 1
        self.vitals.latencies.append(msg.latency_ms)
        self.vitals.publish_times.append(now)
        if reasons:
            self.vitals.last_degraded = (now, reasons)
        rec = self.recorder if item.recorder is self.recorder else None
        if rec is not None:
            rec.write_force(msg)
        for viewer in self.viewers:
            viewer.on_frame(item.frame, msg, self.mesh_msg, rec)

    def _send(self, topic: bytes, msg: Any) -> None:
        try:
            self.pub.send_multipart([topic, msg.SerializeToString()], flags=zmq.NOBLOCK)
        except zmq.Again:
            pass  # PUB drops at the high-water mark; never block the pipeline

    # ---------------------------------------------------------------- control
    def _control_loop(self) -> None:
        poller = zmq.Poller()
        poller.register(self.ctl, zmq.POLLIN)
        period = self.config.network.status_period_s
        next_status = 0.0
        while not self._stop.is_set():
            try:
                events = dict(poller.poll(50))
            except zmq.ZMQError:
                break
            if self.ctl in events:
                try:
                    frames = self.ctl.recv_multipart(zmq.NOBLOCK)
                except zmq.ZMQError:
                    frames = []
                if frames:
                    self._answer(frames)
            now = time.monotonic()
            state = self.state()
            last = self._last_state or (None, None)
            # A new state goes out at once; a new reason within the state (reference capture
            # -> waiting for the first force frame, a stall's growing age) within
            # REASON_REFRESH_S, so a subscriber never reads a stale reason for a whole period.
            reason_due = state[1] != last[1] and now >= next_status - period + REASON_REFRESH_S
            if now >= next_status or state[0] != last[0] or reason_due:
                next_status = now + period
                self._send_status()

    def _send_status(self) -> None:
        """Publish the status now (control loop; stage two before the first force frame)."""
        with self._status_lock:
            self._last_state = self.state()
            msg = self.status_message()
            with self._pub_lock:
                self._send(protocol.status_topic(self.sensor_id), msg)
            if self.recorder is not None:
                self.recorder.write_status(msg)
            for viewer in self.viewers:
                viewer.on_status(msg, self.recorder)

    def _answer(self, frames: list[bytes]) -> None:
        try:
            self.ctl.send_multipart(control.reply_frames(frames, self.handle_request), zmq.NOBLOCK)
        except zmq.ZMQError:
            pass

    # ---------------------------------------------------------------- parts health reads
    # The camera source (None before start), the pressure source's thread (None: pressure
    # carried by the frames), the slot between the stages (its ``dropped`` counts replaced
    # items), the frames collected so far for the (next) reference, a tare not yet done.
    @property
    def camera_source(self) -> Any:
        return self._camera_src

    @property
    def pressure_source(self) -> Any:
        return self._pressure_src

    @property
    def stage_queue(self) -> Mailbox[_Item]:
        return self._mid

    @property
    def reference_collected(self) -> list[Frame]:
        return self._collecting

    @property
    def tare_pending(self) -> bool:
        return self._tare_requested

    # ---------------------------------------------------------------- status
    @property
    def frames_dropped(self) -> int:
        return health.frames_dropped(self)

    def state(self, now: float | None = None) -> tuple[int, str]:
        """(Status.State value, reason)."""
        return health.state(self, now)

    def status_message(self, stopped: bool = False) -> Any:
        return health.status_message(self, stopped)

    def handle_request(self, payload: bytes) -> Any:
        """Answer one serialized ControlRequest (never raises for bad input)."""
        return control.handle_request(self, payload)

    def start_recording(self, path: str, overwrite: bool = False) -> None:
        """Record to the MCAP file ``path`` from now on (raises RecordingPathError with the
        reason: existing file without ``overwrite``, not a regular file, no such folder)."""
        rec = faults.start_recorder(
            path, self.config, self.camera, self.mesh_msg, self._ref_frames, overwrite
        )
        self.vitals.recording_fault_counted = False
        self._cold_next = True
        self.rezero.recording_started()
        self.recorder = rec
