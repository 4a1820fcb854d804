"""The daemon's health: its state (starting, running, degraded, stopped) with the reason, and
the Status message published periodically and answered to get_status."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from bubble_rt.config import DaemonConfig
from bubble_rt.daemon import faults
from bubble_rt.io import protocol
from bubble_rt.io.protocol import pb


@dataclass
class Vitals:
    """What the daemon's threads record for its health and status, shared through one object
    (times are ``time.time()`` seconds)."""

    #: When the daemon started, and when stage one last took a camera frame.
    started_at: float = 0.0
    last_frame_time: float = 0.0
    #: The last degraded frame's time and reasons.
    last_degraded: tuple[float, list[str]] = (0.0, [])
    #: End-to-end latencies (ms) and publish times of the last published frames.
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=2000))
    publish_times: deque[float] = field(default_factory=lambda: deque(maxlen=600))
    #: A recording failure already counted among the errors (counted once per recording).
    recording_fault_counted: bool = False
    #: Frames replaced while no estimator could take them: before the first reference was
    #: installed, and while a tare rebuilt the estimator (not drops: see frames_dropped).
    drops_not_counted: int = 0


class Observed(Protocol):
    """What health reads of the daemon (``bubble_rt.daemon.service.Daemon``): its public
    state and its ``vitals``."""

    config: DaemonConfig
    sensor_id: str
    processor: Any
    recorder: Any
    mesh_msg: Any
    frames_published: int
    errors: dict[str, int]
    last_error: str
    last_error_time: float
    vitals: Vitals
    rezero: Any

    @property
    def camera_source(self) -> Any: ...

    @property
    def pressure_source(self) -> Any: ...

    @property
    def stage_queue(self) -> Any: ...

    @property
    def reference_collected(self) -> list[Any]: ...

    @property
    def tare_pending(self) -> bool: ...

    def report_error(self, kind: str, exc: BaseException | str) -> None: ...


def raw_drops(d: Observed) -> int:
    """Camera frames replaced before stage one took them, plus stage-one results replaced
    before stage two took them, since the daemon started."""
    cam_drops = d.camera_source.output.dropped if d.camera_source is not None else 0
    return cam_drops + d.stage_queue.dropped


def frames_dropped(d: Observed) -> int:
    """Frames the estimator could have processed but never did because a newer one arrived
    first: ``raw_drops`` less those replaced while a reference was installed (the first, and
    each tare: the estimator being built or rebuilt could take none of them)."""
    if d.processor is None:
        return 0
    return raw_drops(d) - d.vitals.drops_not_counted


def state(d: Observed, now: float | None = None) -> tuple[int, str]:
    """(Status.State value, reason) of daemon ``d``."""
    now = time.time() if now is None else now
    cam = d.camera_source
    stall = d.config.camera.stall_timeout_s
    last = d.vitals.last_frame_time or d.vitals.started_at
    cam_reason = ""
    if now - last > stall:
        cam_reason = f"camera stalled: no frame for {now - last:.1f} s"
        if cam is not None and cam.stats.last_error:
            cam_reason += f" ({cam.stats.last_error})"
        if cam is not None and cam.finished.is_set():
            cam_reason = "camera source ended"
    failing = _failing(d, now)
    if d.processor is None:
        if failing:
            return pb.Status.DEGRADED, failing
        reason = f"capturing reference ({len(d.reference_collected)}/{d.config.reference.frames})"
        if d.last_error and now - d.last_error_time < 5.0:
            reason += f"; {d.last_error}"
        if cam_reason:
            reason += f"; {cam_reason}"
        return pb.Status.STARTING, reason
    if cam_reason:
        return pb.Status.DEGRADED, cam_reason
    rec = d.recorder
    if rec is not None and rec.failed:
        if not d.vitals.recording_fault_counted:
            d.vitals.recording_fault_counted = True
            d.report_error("recording", rec.failed)
        return pb.Status.DEGRADED, f"recording failed: {rec.failed}"
    bad = faults.bad_frame_reason(cam, now)
    if bad:
        return pb.Status.DEGRADED, bad
    if d.frames_published == 0:
        if failing:
            return pb.Status.DEGRADED, failing
        reason = "reference captured, waiting for the first force frame"
        if d.last_error:
            reason += f"; {d.last_error}"
        return pb.Status.STARTING, reason
    if d.tare_pending:
        return pb.Status.DEGRADED, "taring: capturing a new reference"
    t_deg, reasons = d.vitals.last_degraded
    if reasons and now - t_deg < 1.0:
        return pb.Status.DEGRADED, "; ".join(reasons)
    if d.last_error and now - d.last_error_time < 2.0:
        return pb.Status.DEGRADED, f"{d.last_error} ({sum(d.errors.values())} errors so far)"
    return pb.Status.RUNNING, ""


#: Errors in a row before a daemon that has not published yet is "degraded", not "starting".
FAILING_AFTER = 3


def _failing(d: Observed, now: float) -> str:
    """The reason a daemon that cannot produce frames gives (keeps failing), else ""."""
    n = sum(d.errors.values())
    if n < FAILING_AFTER or not d.last_error or now - d.last_error_time > 5.0:
        return ""
    return f"cannot produce frames: {d.last_error} ({n} errors so far)"


def status_message(d: Observed, stopped: bool = False) -> Any:
    """The Status message of daemon ``d`` now (``stopped``: the final STOPPED one)."""
    now = time.time()
    st, reason = (pb.Status.STOPPED, "shut down") if stopped else state(d, now)
    recent = [t for t in list(d.vitals.publish_times) if now - t < 5.0]
    rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 2 else 0.0
    rec = d.recorder
    recording, recording_error, recording_dropped = faults.recording_state(rec)
    msg = pb.Status(
        protocol_version=protocol.PROTOCOL_VERSION,
        sensor_id=d.sensor_id,
        state=st,
        reason=reason,
        time_ns=time.time_ns(),
        frame_rate_hz=rate,
        frames_published=d.frames_published,
        frames_dropped=frames_dropped(d),
        recording=recording,
        recording_path=str(rec.path) if rec is not None else "",
        recording_error=recording_error,
        recording_dropped=recording_dropped,
        mesh_id=d.mesh_msg.mesh_id if d.mesh_msg is not None else "",
        uptime_s=now - d.vitals.started_at,
        auto_zero=d.rezero.enabled,
        drift_pa=d.rezero.drift_pa,
        last_rezero_ns=d.rezero.last_ns,
        rezero_count=d.rezero.count,
    )
    lat = np.asarray(list(d.vitals.latencies)[-300:])
    if lat.size:
        p50, p90, p99 = np.percentile(lat, [50, 90, 99])
        msg.latency.p50_ms, msg.latency.p90_ms = float(p50), float(p90)
        msg.latency.p99_ms, msg.latency.max_ms = float(p99), float(lat.max())
    srcs = [d.camera_source] + ([d.pressure_source] if d.pressure_source else [])
    for s in srcs:
        if s is not None:
            faults.add_source_stats(msg, s.stats, now)
    faults.add_daemon_stats(msg, dict(d.errors), d.last_error)
    return msg
