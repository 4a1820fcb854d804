"""The bubble_rt wire protocol (package ``bubble_rt.v1``, see proto/bubble_rt/v1/bubble_rt.proto).

This module is all a client needs: it imports only the generated protobuf code and NumPy,
never the estimator or the C++ core. It converts between protobuf messages and plain
dataclasses holding NumPy arrays (N x 3 arrays in metres / newtons, pressures in pascals,
times in Unix nanoseconds).

Transport (ZeroMQ):
    PUB  multipart [topic, payload]: ``force.<sensor>`` -> ForceFrame,
         ``status.<sensor>`` -> Status.
    Control (ROUTER; use REQ): ControlRequest -> ControlReply, one reply per request.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

try:
    from bubble_rt.proto_gen.bubble_rt.v1 import bubble_rt_pb2 as _pb2
except ImportError as exc:  # pragma: no cover - only without a build
    raise ImportError(
        "bubble_rt's generated protocol code is missing (bubble_rt/proto_gen). Install the "
        "package (bash .ci/install.sh) or run bash .ci/dev-build.sh in a source tree."
    ) from exc

from google.protobuf.message import DecodeError

#: The generated module (typed Any: protoc emits no stubs for mypy).
pb: Any = _pb2

PROTOCOL_VERSION = 1
FORCE_PREFIX = "force."
STATUS_PREFIX = "status."
#: Control requests above this size are refused with an error reply (bytes).
MAX_REQUEST_BYTES = 64 * 1024
#: ZMQ_MAXMSGSIZE of the daemon's control socket (bytes): ZeroMQ itself closes the connection
#: of a peer sending a bigger message, before the daemon sees it, so no reply can come back;
#: :class:`bubble_rt.io.client.Controller` refuses such a request before sending it, with the
#: same kind of error reply. Between MAX_REQUEST_BYTES and this size the daemon replies
#: "request too large".
MAX_MESSAGE_BYTES = 16 * 1024 * 1024


def too_large(size: int) -> str:
    """The error text for a request of ``size`` bytes over the limits."""
    if size > MAX_MESSAGE_BYTES:
        return (
            f"request too large: {size} bytes (limit {MAX_REQUEST_BYTES} bytes; over "
            f"{MAX_MESSAGE_BYTES} bytes, the control socket's ZMQ_MAXMSGSIZE, ZeroMQ drops the "
            "connection without a reply)"
        )
    return f"request too large: {size} bytes (limit {MAX_REQUEST_BYTES} bytes)"


STATE_NAMES = {
    pb.Status.STARTING: "starting",
    pb.Status.RUNNING: "running",
    pb.Status.DEGRADED: "degraded",
    pb.Status.STOPPED: "stopped",
    pb.Status.STATE_UNSPECIFIED: "unknown",
}
STATE_VALUES = {v: k for k, v in STATE_NAMES.items()}

#: Request names accepted on the control socket: the ControlRequest oneof's fields.
REQUESTS: tuple[str, ...] = tuple(
    f.name for f in pb.ControlRequest.DESCRIPTOR.oneofs_by_name["request"].fields
)
#: Parameters ``set_params`` carries: the Params message's fields (the estimator's live
#: parameters, declared in bubble_rt.estimation.params; a test keeps them equal).
PARAM_NAMES: tuple[str, ...] = tuple(f.name for f in pb.Params.DESCRIPTOR.fields)


class ProtocolError(ValueError):
    """Bytes that are not a valid message; the text names the problem."""


def force_topic(sensor_id: str) -> bytes:
    return (FORCE_PREFIX + sensor_id).encode()


def status_topic(sensor_id: str) -> bytes:
    return (STATUS_PREFIX + sensor_id).encode()


def _packed(a: Any) -> list[float]:
    return np.asarray(a, dtype=np.float64).ravel().tolist()


# ---------------------------------------------------------------------------------- mesh
@dataclass(frozen=True)
class MeshData:
    """A decoded Mesh: vertices N x 3 (m), triangles T x 3, boundary (B,), areas (N,) m^2."""

    sensor_id: str
    mesh_id: str
    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    boundary: NDArray[np.int64]
    areas: NDArray[np.float64]

    @property
    def n_nodes(self) -> int:
        return int(self.vertices.shape[0])


def mesh_id_of(vertices: NDArray, triangles: NDArray) -> str:
    """Stable short identifier of a mesh (hex digest of its float64 vertices and int32 triangles)."""
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(triangles, dtype=np.int32).tobytes())
    return h.hexdigest()[:16]


def encode_mesh(
    sensor_id: str,
    vertices: NDArray,
    triangles: NDArray,
    boundary: NDArray,
    areas: NDArray | None = None,
) -> Any:
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    msg = pb.Mesh(protocol_version=PROTOCOL_VERSION, sensor_id=sensor_id, mesh_id=mesh_id_of(v, t))
    msg.vertices.extend(_packed(v))
    msg.triangles.extend(t.ravel().tolist())
    msg.boundary.extend(np.asarray(boundary, dtype=np.int64).ravel().tolist())
    if areas is not None:
        msg.areas.extend(_packed(areas))
    return msg


def decode_mesh(msg: Any) -> MeshData:
    v = np.asarray(msg.vertices, dtype=np.float64)
    t = np.asarray(msg.triangles, dtype=np.int64)
    if v.size % 3 or t.size % 3:
        raise ProtocolError("mesh vertices and triangles must hold multiples of 3 values")
    v = v.reshape(-1, 3)
    t = t.reshape(-1, 3)
    if t.size and t.max() >= len(v):
        raise ProtocolError("mesh triangle index out of range")
    return MeshData(
        sensor_id=msg.sensor_id,
        mesh_id=msg.mesh_id,
        vertices=v,
        triangles=t,
        boundary=np.asarray(msg.boundary, dtype=np.int64),
        areas=np.asarray(msg.areas, dtype=np.float64),
    )


# ---------------------------------------------------------------------------------- force frame
def _empty() -> NDArray[np.float64]:
    return np.zeros(0)


@dataclass(frozen=True)
class Patch:
    """One contact patch (ContactPatch): area-weighted centroid (3,) m, area m^2, force (3,) N,
    node indices; unit outward normal (3,), peak normal pressure Pa, torque about the centroid
    (3,) N m and normal-force-weighted centroid (3,) m. A frame from before these existed
    decodes them as empty arrays and 0 Pa."""

    centroid: NDArray[np.float64]
    area: float
    force: NDArray[np.float64]
    nodes: NDArray[np.int64]
    normal: NDArray[np.float64] = field(default_factory=_empty)
    peak_pressure: float = 0.0
    torque: NDArray[np.float64] = field(default_factory=_empty)
    pressure_centroid: NDArray[np.float64] = field(default_factory=_empty)


@dataclass(frozen=True)
class ForceFrameData:
    """A decoded ForceFrame (arrays: node_forces N x 3 N, normal_pressure (N,) Pa, contact (N,))."""

    sensor_id: str
    seq: int
    frame_index: int
    capture_time_ns: int
    publish_time_ns: int
    mesh_id: str
    net_force: NDArray[np.float64]
    node_forces: NDArray[np.float64]
    normal_pressure: NDArray[np.float64]
    contact: NDArray[np.bool_]
    patches: list[Patch]
    pressure_delta_pa: float
    pressure_pa: float
    timings_ms: dict[str, float]
    latency_ms: float
    solver_status: str
    solver_iterations: int
    valid_node_fraction: float
    degraded: bool
    degraded_reasons: list[str] = field(default_factory=list)
    #: Simulation truth (ForceFrame.sim_truth): the scene's true net force (3,) N and true
    #: contact per mesh node (N,); None unless the frame came from the simulator.
    true_net_force: NDArray[np.float64] | None = None
    true_contact: NDArray[np.bool_] | None = None
    #: Net torque (3,) N m about the mesh origin (ForceFrame.net_torque); None in a frame
    #: from before the field existed.
    net_torque: NDArray[np.float64] | None = None
    #: Node displacements N x 3 m from the Mesh's vertices (ForceFrame.node_displacements);
    #: None in a frame from before the field existed.
    node_displacements: NDArray[np.float64] | None = None

    @property
    def has_truth(self) -> bool:
        """True when the frame carries simulation truth (never for a real sensor)."""
        return self.true_net_force is not None

    def summary(self) -> dict[str, Any]:
        """Plain-JSON summary (what `bubble-rt echo --json` prints)."""
        return {
            "sensor_id": self.sensor_id,
            "seq": self.seq,
            "frame_index": self.frame_index,
            "capture_time_ns": self.capture_time_ns,
            "latency_ms": round(self.latency_ms, 3),
            "net_force": [round(float(x), 5) for x in self.net_force],
            "net_torque": (
                None if self.net_torque is None else [round(float(x), 7) for x in self.net_torque]
            ),
            "contact_nodes": int(self.contact.sum()),
            "patches": [
                {
                    "centroid": [round(float(x), 6) for x in p.centroid],
                    "area": float(p.area),
                    "force": [round(float(x), 5) for x in p.force],
                    "nodes": len(p.nodes),
                    "normal": [round(float(x), 5) for x in p.normal],
                    "peak_pressure": round(float(p.peak_pressure), 2),
                    "torque": [round(float(x), 7) for x in p.torque],
                    "pressure_centroid": [round(float(x), 6) for x in p.pressure_centroid],
                }
                for p in self.patches
            ],
            "pressure_delta_pa": round(self.pressure_delta_pa, 3),
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
            "solver": self.solver_status,
            "degraded": self.degraded,
            "degraded_reasons": list(self.degraded_reasons),
            **({"sim_truth": truth_summary(self)} if self.has_truth else {}),
        }


def truth_summary(frame: ForceFrameData) -> dict[str, Any]:
    """The simulation truth of a decoded frame, plain JSON: true net force, its magnitude,
    true contact nodes and the contact IoU of the estimate against it (None when neither has
    a contact node)."""
    t = np.asarray(frame.true_net_force, dtype=np.float64)
    c = np.asarray(frame.true_contact if frame.true_contact is not None else [], dtype=bool)
    est = np.asarray(frame.contact, dtype=bool)
    union = int((c | est).sum()) if c.shape == est.shape else 0
    iou = int((c & est).sum()) / union if union else None
    return {
        "net_force": [round(float(x), 5) for x in t],
        "force_n": round(float(np.linalg.norm(t)), 5),
        "contact_nodes": int(c.sum()),
        "contact_iou": None if iou is None else round(iou, 4),
    }


def encode_force_frame(
    *,
    sensor_id: str,
    seq: int,
    frame_index: int,
    capture_time_ns: int,
    mesh_id: str,
    net_force: NDArray,
    node_forces: NDArray,
    normal_pressure: NDArray,
    contact: NDArray,
    patches: Sequence[Patch] = (),
    pressure_delta_pa: float = 0.0,
    pressure_pa: float = 0.0,
    timings_ms: Mapping[str, float] | None = None,
    solver_info: Any = None,
    valid_node_fraction: float = 1.0,
    degraded_reasons: Sequence[str] = (),
    net_torque: NDArray | None = None,
    node_displacements: NDArray | None = None,
) -> Any:
    """Build a ForceFrame; publish_time_ns and latency are set by :func:`stamp_publish`.
    ``net_torque`` (3,) N m (bubble_rt.wrench.net_torque) and ``node_displacements`` N x 3 m
    (the positions it was taken at, less the Mesh's vertices); None leaves a field empty."""
    msg = pb.ForceFrame(
        protocol_version=PROTOCOL_VERSION,
        sensor_id=sensor_id,
        seq=int(seq),
        frame_index=int(frame_index),
        capture_time_ns=int(capture_time_ns),
        mesh_id=mesh_id,
        contact=np.asarray(contact, dtype=np.uint8).ravel().tobytes(),
        pressure_delta_pa=float(pressure_delta_pa),
        pressure_pa=float(pressure_pa),
        valid_node_fraction=float(valid_node_fraction),
        degraded=bool(degraded_reasons),
    )
    msg.net_force.extend(_packed(net_force))
    msg.node_forces.extend(_packed(node_forces))
    msg.normal_pressure.extend(_packed(normal_pressure))
    if net_torque is not None:
        msg.net_torque.extend(_packed(net_torque))
    if node_displacements is not None:
        msg.node_displacements.extend(_packed(node_displacements))
    for p in patches:
        peak = float(p.peak_pressure)
        pm = msg.patches.add(area=float(p.area), peak_pressure=peak if np.isfinite(peak) else 0.0)
        pm.centroid.extend(_packed(p.centroid))
        pm.force.extend(_packed(p.force))
        pm.nodes.extend(np.asarray(p.nodes, dtype=np.int64).tolist())
        pm.normal.extend(_packed(p.normal))
        pm.torque.extend(_packed(p.torque))
        pm.pressure_centroid.extend(_packed(p.pressure_centroid))
    for k, v in (timings_ms or {}).items():
        msg.timings.add(stage=str(k), ms=float(v))
    if solver_info is not None:
        msg.solver.status = str(getattr(solver_info, "status", ""))
        msg.solver.iterations = int(getattr(solver_info, "iterations", 0))
        for name in ("primal_residual", "dual_residual", "objective"):
            val = float(getattr(solver_info, name, 0.0))
            setattr(msg.solver, name, val if np.isfinite(val) else 0.0)
    msg.degraded_reasons.extend(list(degraded_reasons))
    return msg


def set_sim_truth(msg: Any, net_force: NDArray, contact: NDArray) -> None:
    """Attach simulation truth to a ForceFrame: the scene's true net force (3,) N and true
    contact per mesh node (N,). Only for frames from the simulator."""
    msg.sim_truth.net_force.extend(_packed(net_force))
    msg.sim_truth.contact = np.asarray(contact, dtype=np.uint8).ravel().tobytes()


def stamp_publish(msg: Any, publish_time_ns: int) -> None:
    """Set the publish time and end-to-end latency (publish - capture) of a frame."""
    msg.publish_time_ns = int(publish_time_ns)
    msg.latency_ms = (publish_time_ns - msg.capture_time_ns) / 1e6


def decode_force_frame(payload: bytes | Any) -> ForceFrameData:
    if isinstance(payload, pb.ForceFrame):
        msg = payload
    else:
        msg = pb.ForceFrame()
        try:
            msg.ParseFromString(payload)
        except DecodeError as exc:
            raise ProtocolError(f"not a ForceFrame: {exc}") from exc
    nf = np.asarray(msg.node_forces, dtype=np.float64)
    if nf.size % 3:
        raise ProtocolError("ForceFrame.node_forces must hold 3 values per node")
    patches = [
        Patch(
            centroid=np.asarray(p.centroid, dtype=np.float64),
            area=p.area,
            force=np.asarray(p.force, dtype=np.float64),
            nodes=np.asarray(p.nodes, dtype=np.int64),
            normal=_vec3_or_empty(p.normal, "ContactPatch.normal"),
            peak_pressure=p.peak_pressure,
            torque=_vec3_or_empty(p.torque, "ContactPatch.torque"),
            pressure_centroid=_vec3_or_empty(p.pressure_centroid, "ContactPatch.pressure_centroid"),
        )
        for p in msg.patches
    ]
    torque = _vec3_or_empty(msg.net_torque, "ForceFrame.net_torque")
    disp = np.asarray(msg.node_displacements, dtype=np.float64)
    if disp.size not in (0, nf.size):
        raise ProtocolError(
            f"ForceFrame.node_displacements must hold 3 values per node ({nf.size}), "
            f"got {disp.size}"
        )
    return ForceFrameData(
        sensor_id=msg.sensor_id,
        seq=msg.seq,
        frame_index=msg.frame_index,
        capture_time_ns=msg.capture_time_ns,
        publish_time_ns=msg.publish_time_ns,
        mesh_id=msg.mesh_id,
        net_force=np.asarray(msg.net_force, dtype=np.float64),
        node_forces=nf.reshape(-1, 3),
        normal_pressure=np.asarray(msg.normal_pressure, dtype=np.float64),
        contact=np.frombuffer(msg.contact, dtype=np.uint8).astype(bool),
        patches=patches,
        pressure_delta_pa=msg.pressure_delta_pa,
        pressure_pa=msg.pressure_pa,
        timings_ms={t.stage: t.ms for t in msg.timings},
        latency_ms=msg.latency_ms,
        solver_status=msg.solver.status,
        solver_iterations=msg.solver.iterations,
        valid_node_fraction=msg.valid_node_fraction,
        degraded=msg.degraded,
        degraded_reasons=list(msg.degraded_reasons),
        net_torque=torque if torque.size else None,
        node_displacements=disp.reshape(-1, 3) if disp.size else None,
        **_decode_sim_truth(msg),
    )


def _vec3_or_empty(values: Any, name: str) -> NDArray[np.float64]:
    """A 3-vector field: 3 values, or none (a message from before the field existed)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size not in (0, 3):
        raise ProtocolError(f"{name} must hold 3 values, got {v.size}")
    return v


def _decode_sim_truth(msg: Any) -> dict[str, Any]:
    if not msg.HasField("sim_truth"):
        return {}
    t = np.asarray(msg.sim_truth.net_force, dtype=np.float64)
    if t.size != 3:
        raise ProtocolError(f"ForceFrame.sim_truth.net_force must hold 3 values, got {t.size}")
    return {
        "true_net_force": t,
        "true_contact": np.frombuffer(msg.sim_truth.contact, dtype=np.uint8).astype(bool),
    }


# ---------------------------------------------------------------------------------- status
@dataclass(frozen=True)
class StatusData:
    """A decoded Status (state one of starting / running / degraded / stopped)."""

    sensor_id: str
    state: str
    reason: str
    time_ns: int
    frame_rate_hz: float
    frames_published: int
    frames_dropped: int
    latency_p50_ms: float
    latency_p90_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    sources: dict[str, dict[str, Any]]
    recording: bool
    recording_path: str
    mesh_id: str
    uptime_s: float
    #: Why the recording stopped writing ("" while fine or not recording).
    recording_error: str = ""
    recording_dropped: int = 0
    #: Re-zeroing on; pressure drift followed since the last tare (Pa); capture time of the
    #: first frame after the last re-zero (Unix ns, 0: none); re-zeros so far.
    auto_zero: bool = False
    drift_pa: float = 0.0
    last_rezero_ns: int = 0
    rezero_count: int = 0


def decode_status(payload: bytes | Any) -> StatusData:
    if isinstance(payload, pb.Status):
        msg = payload
    else:
        msg = pb.Status()
        try:
            msg.ParseFromString(payload)
        except DecodeError as exc:
            raise ProtocolError(f"not a Status: {exc}") from exc
    return StatusData(
        sensor_id=msg.sensor_id,
        state=STATE_NAMES.get(msg.state, "unknown"),
        reason=msg.reason,
        time_ns=msg.time_ns,
        frame_rate_hz=msg.frame_rate_hz,
        frames_published=msg.frames_published,
        frames_dropped=msg.frames_dropped,
        latency_p50_ms=msg.latency.p50_ms,
        latency_p90_ms=msg.latency.p90_ms,
        latency_p99_ms=msg.latency.p99_ms,
        latency_max_ms=msg.latency.max_ms,
        sources={
            s.name: {
                "received": s.received,
                "errors": s.errors,
                "last_error": s.last_error,
                "age_s": s.age_s,
                "error_counts": dict(s.error_counts),
            }
            for s in msg.sources
        },
        recording=msg.recording,
        recording_path=msg.recording_path,
        mesh_id=msg.mesh_id,
        uptime_s=msg.uptime_s,
        recording_error=msg.recording_error,
        recording_dropped=msg.recording_dropped,
        auto_zero=msg.auto_zero,
        drift_pa=msg.drift_pa,
        last_rezero_ns=msg.last_rezero_ns,
        rezero_count=msg.rezero_count,
    )


# ---------------------------------------------------------------------------------- control
def make_request(kind: str, **fields: Any) -> Any:
    """A ControlRequest of the given kind (one of :data:`REQUESTS`).

    ``set_params`` takes keyword parameters from :data:`PARAM_NAMES`; ``record_start`` takes
    ``path``; ``set_auto_zero`` takes ``enabled``.
    """
    if kind not in REQUESTS:
        raise ProtocolError(f"unknown request {kind!r}; expected one of {', '.join(REQUESTS)}")
    req = pb.ControlRequest(protocol_version=PROTOCOL_VERSION)
    if kind == "set_params":
        unknown = set(fields) - set(PARAM_NAMES)
        if unknown:
            raise ProtocolError(f"unknown parameter(s) {sorted(unknown)}; expected {PARAM_NAMES}")
        req.set_params.SetInParent()
        for k, v in fields.items():
            if v is not None:
                setattr(req.set_params, k, float(v))
    elif kind == "record_start":
        req.record_start.path = str(fields.get("path", "") or "")
        req.record_start.overwrite = bool(fields.get("overwrite", False))
    elif kind == "set_auto_zero":
        req.set_auto_zero.enabled = bool(fields.get("enabled", True))
    else:
        getattr(req, kind).SetInParent()
    return req


def parse_request(payload: bytes) -> tuple[str, pb.ControlRequest]:
    """Decode a control request; raises :class:`ProtocolError` naming the problem."""
    if len(payload) > MAX_REQUEST_BYTES:
        raise ProtocolError(too_large(len(payload)))
    req = pb.ControlRequest()
    try:
        req.ParseFromString(payload)
    except DecodeError as exc:
        raise ProtocolError(
            f"malformed request: not a bubble_rt.v1.ControlRequest ({exc})"
        ) from exc
    if req.protocol_version not in (0, PROTOCOL_VERSION):
        raise ProtocolError(
            f"unsupported protocol_version {req.protocol_version} (this daemon speaks "
            f"{PROTOCOL_VERSION})"
        )
    kind = req.WhichOneof("request")
    if kind is None:
        raise ProtocolError(
            f"unknown or empty request: set one of {', '.join(REQUESTS)} in ControlRequest"
        )
    return kind, req


def params_dict(p: Any) -> dict[str, float]:
    """The fields set in a Params message."""
    return {name: getattr(p, name) for name in PARAM_NAMES if p.HasField(name)}


def error_reply(text: str) -> Any:
    return pb.ControlReply(protocol_version=PROTOCOL_VERSION, ok=False, error=text)


def ok_reply(**payload: Any) -> Any:
    rep = pb.ControlReply(protocol_version=PROTOCOL_VERSION, ok=True)
    for k, v in payload.items():
        if isinstance(v, str):
            setattr(rep, k, v)
        else:
            getattr(rep, k).CopyFrom(v)
    if not payload:
        rep.done.SetInParent()
    return rep


def parse_reply(payload: bytes) -> Any:
    rep = pb.ControlReply()
    try:
        rep.ParseFromString(payload)
    except DecodeError as exc:
        raise ProtocolError(f"malformed reply: {exc}") from exc
    return rep
