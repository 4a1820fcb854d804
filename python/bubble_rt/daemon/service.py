"""The streaming daemon: sensor frames in, force and contact frames out over ZeroMQ.

Threads (all daemon threads, all loops bounded by timeouts so shutdown takes < 2 s):

* capture: one per source (``bubble_rt.daemon.sources``), feeding a one-item latest-value slot
  (camera) or a pressure ring buffer;
* stage 1: takes the newest camera frame, pairs it with the pressure interpolated at its
  capture time, captures the reference (first K frames, and again on ``tare``) and tracks
  the membrane deformation (optical flow + lifting, C++ without the GIL);
* stage 2: solves for the forces (C++ ADMM without the GIL), derives contact patches and
  publishes the ForceFrame, so the flow of frame k+1 overlaps the solve of frame k;
* control: answers ControlRequests on a ROUTER socket and publishes Status periodically.

Frames that arrive while a stage is busy replace older unprocessed ones (counted as drops):
the daemon always works on the newest data and its latency never builds up.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import zmq
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.config import LIVE_PARAMS, DaemonConfig, param_problem
from bubble_rt.daemon import faults
from bubble_rt.daemon.sources import (
    CameraSource,
    LatestSlot,
    PressureBuffer,
    ThreadedSource,
    make_camera_source,
    make_pressure_source,
    pair_pressure,
)
from bubble_rt.frames import Frame
from bubble_rt.io import protocol
from bubble_rt.io.protocol import pb
from bubble_rt.mesh import Mesh

#: Largest message the control socket accepts at the transport level (ZMQ_MAXMSGSIZE; bigger:
#: ZeroMQ drops the connection, see ``protocol.MAX_MESSAGE_BYTES``).
CONTROL_MAX_TRANSPORT_BYTES = protocol.MAX_MESSAGE_BYTES


class Processor(Protocol):
    """What the daemon needs from the estimation side (a real estimator or a test fake)."""

    mesh: Mesh

    def stage1(self, frame: Frame) -> Any:
        """Deformation of one frame (may run concurrently with ``stage2`` of an older one)."""

    def stage2(self, frame: Frame, data: Any) -> Any:
        """An ``Estimate`` (node_forces, normal_pressure, contact, net_force, info, ...)."""

    def set_reference(self, frames: list[Frame]) -> None:
        """Re-capture the reference from untouched frames (tare)."""

    def reconfigure(self, params: dict[str, float]) -> None:
        """Apply Params (k_f, k_u, youngs_modulus, k_const, k_linear) between frames."""


ProcessorFactory = Callable[[DaemonConfig, Camera, list[Frame]], Processor]


# ------------------------------------------------------------------------ real estimator
class EstimatorProcessor:
    """The real pipeline: Reference -> fit_mesh -> DeformationTracker + make_estimator."""

    def __init__(self, config: DaemonConfig, camera: Camera, frames: list[Frame]) -> None:
        from bubble_rt.estimation.deformation import Reference
        from bubble_rt.estimation.estimator import EstimatorConfig
        from bubble_rt.estimation.membrane import Material

        ec = config.estimator
        self.config = config
        self.camera = camera
        self.kind = ec.kind
        reference = Reference.capture(frames)
        template = (
            Mesh.preset(ec.mesh) if ec.mesh in ("coarse", "medium", "fine") else Mesh.load(ec.mesh)
        )
        if ec.fit_mesh:
            from bubble_rt.estimation.fitting import fit_mesh

            self.mesh = fit_mesh(template, reference, camera)
        else:
            self.mesh = template
        self.est_config = EstimatorConfig(
            material=Material(E=ec.youngs_modulus, nu=ec.poisson, thickness=ec.thickness),
            k_f=ec.k_f,
            k_u=ec.k_u,
            k_const=ec.k_const,
            k_linear=ec.k_linear,
            solver=self._solver_settings(),
        )
        self._build(reference)

    def _solver_settings(self) -> Any:
        from bubble_rt.estimation.solver import SolverSettings

        sc = self.config.solver
        wanted: dict[str, Any] = {"time_limit": sc.time_limit_ms / 1e3}
        names = {f.name for f in dataclasses.fields(SolverSettings)}
        return SolverSettings(**{k: v for k, v in wanted.items() if k in names})

    def _flow_settings(self) -> Any:
        from bubble_rt.estimation.deformation import FlowSettings

        names = {f.name for f in dataclasses.fields(FlowSettings)}
        wanted = dataclasses.asdict(self.config.flow)
        return FlowSettings(**{k: v for k, v in wanted.items() if k in names})

    def _build(self, reference: Any, estimator: bool = True) -> None:
        from bubble_rt.estimation.estimator import make_estimator

        self.reference = reference
        if estimator:
            self.estimator = make_estimator(
                self.kind, self.mesh, self.est_config, camera=self.camera, reference=reference
            )
        if self.kind == "fem":
            from bubble_rt.estimation.deformation import DeformationTracker

            self.tracker = DeformationTracker(
                self.mesh, self.camera, reference, self._flow_settings()
            )

    def stage1(self, frame: Frame) -> Any:
        return self.tracker.track(frame) if self.kind == "fem" else None

    def stage2(self, frame: Frame, data: Any) -> Any:
        if self.kind != "fem":
            return self.estimator.process(frame)
        est = self.estimator.estimate(data.U, data.dp)
        timings = dict(getattr(data, "timings_ms", {}) or {})
        timings.update(est.timings_ms or {})
        return replace(est, timings_ms=timings, valid_node_fraction=data.valid_fraction)

    def set_reference(self, frames: list[Frame]) -> None:
        from bubble_rt.estimation.deformation import Reference

        # The FEM estimator depends on the mesh only: keep it (and its factorisation).
        self._build(Reference.capture(frames), estimator=self.kind != "fem")

    def reconfigure(self, params: dict[str, float]) -> None:
        changes: dict[str, Any] = {k: v for k, v in params.items() if k != "youngs_modulus"}
        if "youngs_modulus" in params:
            changes["material"] = replace(self.est_config.material, E=params["youngs_modulus"])
        self.est_config = replace(self.est_config, **changes)
        if hasattr(self.estimator, "reconfigure"):
            self.estimator.reconfigure(**changes)
        else:  # an estimator without live reconfiguration: rebuild it
            self._build(self.reference)


# ------------------------------------------------------------------------ mesh helpers
def lumped_areas(vertices: NDArray, triangles: NDArray) -> NDArray[np.float64]:
    """(N,) lumped node areas: a third of every incident triangle's area, m^2."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    a = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    out = np.zeros(len(v))
    for k in range(3):
        np.add.at(out, t[:, k], a / 3.0)
    return out


class PatchFinder:
    """Contact patches: connected components of the contact mask over mesh edges."""

    def __init__(self, mesh: Mesh) -> None:
        import scipy.sparse as sp

        t = np.asarray(mesh.triangles)
        n = mesh.n_nodes
        i = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
        j = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
        self.adjacency = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.areas = lumped_areas(mesh.vertices, mesh.triangles)

    def patches(
        self, contact: NDArray, node_forces: NDArray, displacements: NDArray | None = None
    ) -> list[protocol.Patch]:
        from scipy.sparse.csgraph import connected_components

        idx = np.flatnonzero(np.asarray(contact, dtype=bool))
        if idx.size == 0:
            return []
        sub = self.adjacency[idx][:, idx]
        n_comp, labels = connected_components(sub, directed=False)
        pos = self.vertices if displacements is None else self.vertices + displacements
        out = []
        for c in range(n_comp):
            nodes = idx[labels == c]
            a = self.areas[nodes]
            area = float(a.sum())
            w = a / area if area > 0 else np.full(len(nodes), 1.0 / len(nodes))
            out.append(
                protocol.Patch(
                    centroid=w @ pos[nodes],
                    area=area,
                    force=np.asarray(node_forces, dtype=np.float64)[nodes].sum(axis=0),
                    nodes=nodes.astype(np.int64),
                )
            )
        out.sort(key=lambda p: -float(np.linalg.norm(p.force)))
        return out


# ------------------------------------------------------------------------ daemon
@dataclass
class _Item:
    frame: Frame
    reasons: list[str]
    data: Any
    timings: dict[str, float] = field(default_factory=dict)
    t_stage1_end: float = 0.0


class DaemonError(RuntimeError):
    """The daemon cannot start (socket in use, source missing, ...)."""


PARAM_CONFIG_KEYS = {k: k for k in LIVE_PARAMS}


def validate_params(params: dict[str, float]) -> str | None:
    """None when the Params are acceptable, else the error text naming the parameter.

    The ranges are the configuration's (``bubble_rt.config.ESTIMATOR_RANGES``): nothing is
    applied unless every value given is acceptable.
    """
    if not params:
        return "set_params: no parameter given (set one of " + ", ".join(PARAM_CONFIG_KEYS) + ")"
    for k, v in params.items():
        err = param_problem(k, v)
        if err:
            return f"set_params: {k} {err}"
    return None


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
        self.processor: Processor | None = None
        self.mesh_msg: Any | None = None
        self._patches: PatchFinder | None = None
        self._mid: LatestSlot[_Item] = LatestSlot()
        self._pending_params: dict[str, float] = {}
        self._tare_requested = False
        self._ref_frames: list[Frame] = []
        self._collecting: list[Frame] = []
        self.recorder: Any = None
        self._recording_fault_counted = False
        self.seq = 0
        self.frames_published = 0
        self.errors: dict[str, int] = {}
        self.last_error = ""
        self.last_error_time = 0.0
        self._latencies: deque[float] = deque(maxlen=2000)
        self._publish_times: deque[float] = deque(maxlen=600)
        self._last_frame_time = 0.0
        self._last_degraded: tuple[float, list[str]] = (0.0, [])
        self._started_at = 0.0
        self._last_state: tuple[int, str] | None = None
        self.ctx: zmq.Context | None = None

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> Daemon:
        cfg = self.config
        self._started_at = time.time()
        if cfg.processing.opencv_threads > 0:
            # Read once when the C++ core loads (its first import happens below or later).
            os.environ.setdefault("OPENCV_FOR_THREADS_NUM", str(cfg.processing.opencv_threads))
        if self._camera_src is None:
            self._camera_src = make_camera_source(cfg.camera)
        cam = self._camera_src
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
                self._start_recording(cfg.recording.path, cfg.recording.overwrite)
            except ValueError as exc:
                self._close_sockets()
                raise DaemonError(f"cannot record: {exc}") from exc
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
            self._camera_src.stop(0.2)
        if self._pressure_arg is not None and self._pressure_arg[1] is not None:
            self._pressure_arg[1].stop(0.2)
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))
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
    def _error(self, kind: str, exc: BaseException | str) -> None:
        text = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
        with self._state_lock:
            self.errors[kind] = self.errors.get(kind, 0) + 1
            self.last_error = f"{kind}: {text}"
            self.last_error_time = time.time()

    # ---------------------------------------------------------------- stage 1
    def _stage1_loop(self) -> None:
        cam = self._camera_src
        assert cam is not None
        cfg = self.config
        k = cfg.reference.frames
        try:
            given = cam.reference_frames(k)
        except Exception as exc:
            self._error("reference", exc)
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
            self._last_frame_time = t_take
            frame, reasons = pair_pressure(
                frame, self.pressure_buffer, cfg.pressure.stale_timeout_s
            )
            if self.processor is None or self._tare_requested:
                self._collecting.append(frame)
                if len(self._collecting) >= k:
                    frames, self._collecting = self._collecting, []
                    self._install_reference(frames)
                continue
            if self.recorder is not None:
                self.recorder.write_frame(frame)
            timings = {"wait": (t_take - frame.t) * 1e3}
            t0 = time.perf_counter()
            try:
                data = self.processor.stage1(frame)
            except Exception as exc:
                self._error("deformation", exc)
                continue
            timings["stage1"] = (time.perf_counter() - t0) * 1e3
            item = _Item(frame, reasons, data, timings, time.perf_counter())
            if two_stage:
                self._mid.put(item, block=cam.lossless, stop=self._stop)
            else:
                self._finish(item)

    def _install_reference(self, frames: list[Frame]) -> None:
        try:
            if self.processor is None:
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
                    self.recorder.write_message(recording_topic("mesh"), self.mesh_msg)
            else:
                with self._proc_lock:
                    self.processor.set_reference(frames)
            self._ref_frames = frames
            if self.recorder is not None:
                self.recorder.write_reference(frames)
        except Exception as exc:
            self._error("reference", exc)
        finally:
            self._tare_requested = False

    # ---------------------------------------------------------------- stage 2
    def _stage2_loop(self) -> None:
        while not self._stop.is_set():
            item = self._mid.get(timeout=0.1)
            if item is not None:
                self._finish(item)

    def _finish(self, item: _Item) -> None:
        proc = self.processor
        if proc is None or self._patches is None or self.mesh_msg is None:
            return
        item.timings["queue"] = (time.perf_counter() - item.t_stage1_end) * 1e3
        t0 = time.perf_counter()
        try:
            with self._state_lock:
                params, self._pending_params = self._pending_params, {}
            with self._proc_lock:
                if params:
                    proc.reconfigure(params)
                est = proc.stage2(item.frame, item.data)
            timings = dict(item.timings)
            for key, v in (getattr(est, "timings_ms", None) or {}).items():
                timings[key] = float(v)
            contact = np.asarray(est.contact, dtype=bool)
            forces = np.asarray(est.node_forces, dtype=np.float64)
            patches = self._patches.patches(contact, forces, getattr(est, "displacements", None))
            reasons = list(item.reasons)
            vf = float(getattr(est, "valid_node_fraction", 1.0))
            if vf < 0.5:
                reasons.append(f"only {vf:.0%} of nodes tracked")
            for problem in (
                faults.solver_problem(getattr(est, "info", None)),
                faults.forces_problem(forces, est.net_force),
            ):
                if problem:
                    reasons.append(problem)
            timings["stage2"] = (time.perf_counter() - t0) * 1e3
            dp = getattr(item.data, "dp", None)
            if dp is None:
                ref_p = getattr(getattr(proc, "reference", None), "pressure_pa", None)
                dp = item.frame.pressure_pa - ref_p if ref_p is not None else 0.0
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
                pressure_delta_pa=float(dp),
                pressure_pa=float(item.frame.pressure_pa),
                timings_ms=timings,
                solver_info=getattr(est, "info", None),
                valid_node_fraction=vf,
                degraded_reasons=reasons,
            )
        except Exception as exc:
            self._error("estimator", exc)
            return
        now = time.time()
        protocol.stamp_publish(msg, time.time_ns())
        with self._pub_lock:
            self._send(protocol.force_topic(self.sensor_id), msg)
        self.seq += 1
        self.frames_published += 1
        self._latencies.append(msg.latency_ms)
        self._publish_times.append(now)
        if reasons:
            self._last_degraded = (now, reasons)
        rec = self.recorder
        if rec is not None:
            rec.write_force(msg)

    def _send(self, topic: bytes, msg: Any) -> None:
        try:
            self.pub.send_multipart([topic, msg.SerializeToString()], flags=zmq.NOBLOCK)
        except zmq.Again:
            pass  # PUB drops at the high-water mark; never block the pipeline

    # ---------------------------------------------------------------- status
    @property
    def frames_dropped(self) -> int:
        cam_drops = self._camera_src.output.dropped if self._camera_src is not None else 0
        return cam_drops + self._mid.dropped

    def state(self, now: float | None = None) -> tuple[int, str]:
        """(Status.State value, reason)."""
        now = time.time() if now is None else now
        cam = self._camera_src
        stall = self.config.camera.stall_timeout_s
        last = self._last_frame_time or self._started_at
        cam_reason = ""
        if now - last > stall:
            cam_reason = f"camera stalled: no frame for {now - last:.1f} s"
            if cam is not None and cam.stats.last_error:
                cam_reason += f" ({cam.stats.last_error})"
            if cam is not None and cam.finished.is_set():
                cam_reason = "camera source ended"
        if self.processor is None:
            reason = f"capturing reference ({len(self._collecting)}/{self.config.reference.frames})"
            if self.last_error and now - self.last_error_time < 5.0:
                reason += f"; {self.last_error}"
            if cam_reason:
                reason += f"; {cam_reason}"
            return pb.Status.STARTING, reason
        if cam_reason:
            return pb.Status.DEGRADED, cam_reason
        rec = self.recorder
        if rec is not None and rec.failed:
            if not self._recording_fault_counted:
                self._recording_fault_counted = True
                self._error("recording", rec.failed)
            return pb.Status.DEGRADED, f"recording failed: {rec.failed}"
        bad = faults.bad_frame_reason(cam, now)
        if bad:
            return pb.Status.DEGRADED, bad
        if self.frames_published == 0:
            reason = "reference captured, waiting for the first force frame"
            if self.last_error:
                reason += f"; {self.last_error}"
            return pb.Status.STARTING, reason
        if self._tare_requested:
            return pb.Status.DEGRADED, "taring: capturing a new reference"
        t_deg, reasons = self._last_degraded
        if reasons and now - t_deg < 1.0:
            return pb.Status.DEGRADED, "; ".join(reasons)
        if self.last_error and now - self.last_error_time < 2.0:
            return pb.Status.DEGRADED, self.last_error
        return pb.Status.RUNNING, ""

    def status_message(self, stopped: bool = False) -> Any:
        now = time.time()
        state, reason = (pb.Status.STOPPED, "shut down") if stopped else self.state(now)
        recent = [t for t in list(self._publish_times) if now - t < 5.0]
        rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 2 else 0.0
        msg = pb.Status(
            protocol_version=protocol.PROTOCOL_VERSION,
            sensor_id=self.sensor_id,
            state=state,
            reason=reason,
            time_ns=time.time_ns(),
            frame_rate_hz=rate,
            frames_published=self.frames_published,
            frames_dropped=self.frames_dropped,
            recording=faults.recording_state(self.recorder)[0],
            recording_path=str(self.recorder.path) if self.recorder is not None else "",
            recording_error=faults.recording_state(self.recorder)[1],
            recording_dropped=faults.recording_state(self.recorder)[2],
            mesh_id=self.mesh_msg.mesh_id if self.mesh_msg is not None else "",
            uptime_s=now - self._started_at,
        )
        lat = np.asarray(list(self._latencies)[-300:])
        if lat.size:
            p50, p90, p99 = np.percentile(lat, [50, 90, 99])
            msg.latency.p50_ms, msg.latency.p90_ms = float(p50), float(p90)
            msg.latency.p99_ms, msg.latency.max_ms = float(p99), float(lat.max())
        srcs = [self._camera_src] + ([self._pressure_src] if self._pressure_src else [])
        for s in srcs:
            if s is not None:
                faults.add_source_stats(msg, s.stats, now)
        faults.add_daemon_stats(msg, dict(self.errors), self.last_error)
        return msg

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
            if now >= next_status or state[0] != (self._last_state or (None,))[0]:
                self._last_state = state
                next_status = now + period
                msg = self.status_message()
                with self._pub_lock:
                    self._send(protocol.status_topic(self.sensor_id), msg)
                if self.recorder is not None:
                    self.recorder.write_status(msg)

    def _answer(self, frames: list[bytes]) -> None:
        ident, rest = frames[0], frames[1:]
        envelope = [ident]
        if rest and rest[0] == b"":
            envelope.append(b"")
            rest = rest[1:]
        if len(rest) != 1:
            reply = protocol.error_reply(
                f"malformed request: expected exactly one message frame, got {len(rest)}"
            )
        else:
            try:
                reply = self.handle_request(rest[0])
            except Exception as exc:  # the daemon never dies on a request
                reply = protocol.error_reply(f"internal error: {type(exc).__name__}: {exc}")
        try:
            self.ctl.send_multipart(envelope + [reply.SerializeToString()], flags=zmq.NOBLOCK)
        except zmq.ZMQError:
            pass

    def handle_request(self, payload: bytes) -> Any:
        """Answer one serialized ControlRequest (never raises for bad input)."""
        try:
            kind, req = protocol.parse_request(payload)
        except protocol.ProtocolError as exc:
            return protocol.error_reply(str(exc))
        if kind == "get_mesh":
            if self.mesh_msg is None:
                return protocol.error_reply(
                    "mesh not ready: the daemon is still capturing the reference frames"
                )
            return protocol.ok_reply(mesh=self.mesh_msg)
        if kind == "get_config":
            return protocol.ok_reply(config_toml=self.config.to_toml())
        if kind == "get_status":
            return protocol.ok_reply(status=self.status_message())
        if kind == "set_params":
            params = protocol.params_dict(req.set_params)
            err = validate_params(params)
            if err:
                return protocol.error_reply(err)
            with self._state_lock:
                self._pending_params.update(params)
                est = replace(self.config.estimator, **params)  # type: ignore[arg-type]
                self.config = replace(self.config, estimator=est)
            out = pb.Params(**{k: getattr(est, k) for k in PARAM_CONFIG_KEYS})
            return protocol.ok_reply(params=out)
        if kind == "tare":
            if self.processor is None:
                return protocol.error_reply("tare: the reference is still being captured")
            self._collecting = []
            self._tare_requested = True
            return protocol.ok_reply()
        if kind == "record_start":
            rec = self.recorder
            if rec is not None and not rec.failed:
                return protocol.error_reply(f"already recording to {rec.path}")
            try:
                path = faults.recording_path(req.record_start.path, self.config.recording.directory)
                self._start_recording(str(path), req.record_start.overwrite)
            except Exception as exc:
                return protocol.error_reply(f"record_start: refused: {exc}")
            if rec is not None:  # a failed recording is replaced by the new one
                rec.close(timeout=0.0)
            return protocol.ok_reply(recording_path=str(path.resolve()))
        if kind == "record_stop":
            rec = self.recorder
            if rec is None:
                return protocol.error_reply("record_stop: not recording")
            self.recorder = None
            ok, text = faults.stop_recorder(rec)
            if not ok:
                return protocol.error_reply(text)
            return protocol.ok_reply(recording_path=text)
        return protocol.error_reply(f"unknown request {kind!r}")  # pragma: no cover

    def _start_recording(self, path: str, overwrite: bool = False) -> None:
        rec = faults.start_recorder(
            path, self.config, self.camera, self.mesh_msg, self._ref_frames, overwrite
        )
        self._recording_fault_counted = False
        self.recorder = rec


def recording_topic(name: str) -> str:
    from bubble_rt.io import mcap as recording

    return {"mesh": recording.TOPIC_MESH}[name]


def run(config: DaemonConfig, stop: threading.Event, **kwargs: Any) -> Daemon:
    """Start a daemon and block until ``stop`` is set; returns the stopped daemon."""
    d = Daemon(config, **kwargs).start()
    try:
        while not stop.wait(0.1):
            pass
    finally:
        d.stop()
    return d
