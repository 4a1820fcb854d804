"""Foxglove out: the force field as a 3D scene, plots, the image and the status.

``bubble-rt serve --foxglove [ADDR]`` (default ``ws://127.0.0.1:8765``) serves these channels
over the Foxglove WebSocket protocol with the ``foxglove-sdk`` package, beside the ZeroMQ
stream; with ``--record`` the same channels also go into the MCAP file, so a recording opened
in Foxglove shows the same. Off by default.

==============================  ==========================  =====================================
topic                           schema (encoding)           content
==============================  ==========================  =====================================
/bubble_rt/foxglove/scene       foxglove.SceneUpdate (pb)   entity ``membrane``: mesh at its
                                                            measured shape, vertices coloured by
                                                            normal contact pressure; ``forces``:
                                                            node force arrows; ``contact``:
                                                            contact nodes, patch labels and
                                                            outlines; ``wrench``: net force
                                                            and torque arrows
/bubble_rt/foxglove/net_force   bubble_rt.NetForce (json)   estimated net force x, y, z,
                                                            magnitude (N, sensor frame)
/bubble_rt/foxglove/true_force  bubble_rt.NetForce (json)   the simulator's true net force (sim
                                                            scenes only)
/bubble_rt/foxglove/image       foxglove.CompressedImage    colour image, JPEG, at most
                                (pb)                        ``image_hz``
/bubble_rt/foxglove/status      bubble_rt.Status (json)     state, reason, rate, latency
==============================  ==========================  =====================================

Everything is in the frame ``bubble_rt_sensor`` (the mesh frame: rim plane z = 0, dome
towards +z). Scene conventions:

* colour: normal contact pressure (inward positive) mapped linearly from 0 (grey-blue) over
  yellow (half) to ``pressure_max_pa`` (default 5 kPa, red); above it is clamped to red.
* arrows: one per contact node (``arrows="all"``: every node off the rim, whose forces are
  its support, not contact) whose force exceeds ``min_arrow_n`` (0.01 N), drawn as the force
  acting on the membrane: the tip at the node, the arrow along the force, its length
  ``arrow_scale`` x |f| (default 0.05 m per N, i.e. 5 mm per 0.1 N).
* contact: every contact node as a yellow 2 mm sphere; each contact patch (the contact nodes
  of one load, as published) a text at its centroid, ``patch k: |F| N``, and its outline
  (yellow lines: the edges between patch nodes that fewer than two of the patch's triangles
  share).
* wrench (frames with a net torque): the net force as a blue arrow on its line of action (the
  wrench's central axis, ``F x tau / |F|^2 + s F``), its tip at the axis point nearest the
  strongest patch's centroid (else nearest the origin), ``arrow_scale`` long per newton; the
  net torque about the origin as a purple arrow from the origin, ``torque_scale`` (default
  1 m per N m, i.e. 10 mm per 0.01 N m).

``layouts/bubble_rt.foxglove.json`` in the repository is a Foxglove layout (3D, image, plots,
status) for these topics.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import numpy as np
from numpy.typing import NDArray

FRAME_ID = "bubble_rt_sensor"
TOPIC_SCENE = "/bubble_rt/foxglove/scene"
TOPIC_NET_FORCE = "/bubble_rt/foxglove/net_force"
TOPIC_TRUE_FORCE = "/bubble_rt/foxglove/true_force"
TOPIC_IMAGE = "/bubble_rt/foxglove/image"
TOPIC_STATUS = "/bubble_rt/foxglove/status"
DEFAULT_ADDRESS = "ws://127.0.0.1:8765"

ARROW_SCALE_M_PER_N = 0.05
TORQUE_SCALE_M_PER_NM = 1.0
MIN_ARROW_N = 0.01
PRESSURE_MAX_PA = 5000.0

NET_FORCE_SCHEMA = {
    "title": "bubble_rt.NetForce",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "frame_index": {"type": "integer"},
        "x": {"type": "number"},
        "y": {"type": "number"},
        "z": {"type": "number"},
        "magnitude": {"type": "number"},
    },
}
STATUS_SCHEMA = {
    "title": "bubble_rt.Status",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object"},
        "state": {"type": "string"},
        "reason": {"type": "string"},
        "frame_rate_hz": {"type": "number"},
        "frames_published": {"type": "integer"},
        "frames_dropped": {"type": "integer"},
        "latency_p50_ms": {"type": "number"},
        "latency_p99_ms": {"type": "number"},
    },
}


@dataclass
class Encoded:
    """One serialised message with its schema: what both the WebSocket channel and the MCAP
    recorder need (``SerializeToString`` lets :class:`bubble_rt.io.mcap_writer.Recorder` take it)."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    data: bytes
    log_time_ns: int

    def SerializeToString(self) -> bytes:  # noqa: N802 (protobuf-like)
        return self.data


def _proto(topic: str, msg: Any, t_ns: int) -> Encoded:
    s = type(msg).get_schema()
    return Encoded(topic, s.name, s.encoding, bytes(s.data), "protobuf", msg.encode(), t_ns)


def _json(topic: str, schema: dict[str, Any], payload: dict[str, Any], t_ns: int) -> Encoded:
    return Encoded(
        topic,
        schema["title"],
        "jsonschema",
        json.dumps(schema).encode(),
        "json",
        json.dumps(payload).encode(),
        t_ns,
    )


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def pressure_colors(p: NDArray, p_max: float = PRESSURE_MAX_PA) -> NDArray[np.float64]:
    """RGBA (n x 4, 0..1) of normal pressures: 0 -> grey-blue, p_max and above -> red."""
    s = np.clip(np.nan_to_num(np.asarray(p, dtype=np.float64)) / p_max, 0.0, 1.0)[:, None]
    lo = np.array([0.55, 0.62, 0.75, 1.0])
    mid = np.array([1.0, 0.85, 0.2, 1.0])
    hi = np.array([0.85, 0.1, 0.1, 1.0])
    a = np.clip(2 * s, 0, 1)
    b = np.clip(2 * s - 1, 0, 1)
    return np.where(s < 0.5, lo + (mid - lo) * a, mid + (hi - mid) * b)


def _quat_x_to(d: NDArray) -> tuple[float, float, float, float]:
    """(x, y, z, w) rotating +x onto unit vector d."""
    x = np.array([1.0, 0.0, 0.0])
    c = float(np.dot(x, d))
    if c < -0.999999:
        return 0.0, 0.0, 1.0, 0.0
    axis = np.cross(x, d)
    q = np.array([axis[0], axis[1], axis[2], 1.0 + c])
    q /= np.linalg.norm(q)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def scene_update(
    vertices: NDArray,
    triangles: NDArray,
    node_forces: NDArray,
    normal_pressure: NDArray,
    contact: NDArray,
    patches: list[Any] | None = None,
    *,
    boundary: NDArray | None = None,
    arrows_for: str = "contact",
    t_ns: int = 0,
    arrow_scale: float = ARROW_SCALE_M_PER_N,
    min_arrow_n: float = MIN_ARROW_N,
    pressure_max_pa: float = PRESSURE_MAX_PA,
    net_force: NDArray | None = None,
    net_torque: NDArray | None = None,
    torque_scale: float = TORQUE_SCALE_M_PER_NM,
) -> Any:
    """The foxglove.SceneUpdate for one force frame (see the module docstring); the wrench
    entity only when ``net_force`` and ``net_torque`` (3,) are given."""
    import foxglove.messages as fm

    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(node_forces, dtype=np.float64).reshape(-1, 3)
    C = np.asarray(contact, dtype=bool).reshape(-1)
    T = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    stamp = fm.Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))

    def entity(name: str, **primitives: Any) -> Any:
        return fm.SceneEntity(timestamp=stamp, frame_id=FRAME_ID, id=name, **primitives)

    mags = np.linalg.norm(F, axis=1)
    if arrows_for == "contact":
        mags[~C] = 0.0
    if boundary is not None:
        mags[np.asarray(boundary, dtype=np.int64)] = 0.0  # the rim's support, not contact
    red = fm.Color(r=0.9, g=0.15, b=0.1, a=1.0)
    arrows = [
        _arrow(fm, V[i], F[i], arrow_scale, red, 0.0008) for i in np.flatnonzero(mags > min_arrow_n)
    ]
    entities = [
        entity("membrane", triangles=[_membrane(fm, V, T, normal_pressure, pressure_max_pa)]),
        entity("forces", arrows=arrows),
        entity("contact", **_contact(fm, V, T, C, patches or [])),
    ]
    if net_force is not None and net_torque is not None:
        wrench = _wrench_arrows(
            fm, net_force, net_torque, patches, arrow_scale, min_arrow_n, torque_scale
        )
        entities.append(entity("wrench", arrows=wrench))
    return fm.SceneUpdate(entities=entities)


def _pose(fm: Any, at: NDArray, q: tuple[float, float, float, float] = (0, 0, 0, 1)) -> Any:
    return fm.Pose(
        position=fm.Vector3(x=float(at[0]), y=float(at[1]), z=float(at[2])),
        orientation=fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _points(fm: Any, P: NDArray) -> list[Any]:
    return [fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in P]


def _arrow(fm: Any, tip: NDArray, vec: NDArray, scale: float, color: Any, width: float) -> Any:
    """An arrow ending at ``tip`` along ``vec``, ``scale`` metres per unit of its length."""
    mag = float(np.linalg.norm(vec))
    d = vec / mag
    length = mag * scale
    head = min(0.3 * length, 2 * width + 0.002)
    return fm.ArrowPrimitive(
        pose=_pose(fm, tip - d * length, _quat_x_to(d)),
        shaft_length=max(length - head, 0.0),
        shaft_diameter=width,
        head_length=head,
        head_diameter=2.5 * width,
        color=color,
    )


def _membrane(
    fm: Any, V: NDArray, T: NDArray, normal_pressure: NDArray, pressure_max_pa: float
) -> Any:
    """The membrane's triangles, coloured by normal pressure."""
    cols = pressure_colors(normal_pressure, pressure_max_pa)
    return fm.TriangleListPrimitive(
        pose=_pose(fm, np.zeros(3)),
        points=_points(fm, V),
        colors=[fm.Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=1.0) for c in cols],
        indices=[int(i) for i in T.reshape(-1)],
    )


def _contact(fm: Any, V: NDArray, T: NDArray, C: NDArray, patches: list[Any]) -> dict[str, Any]:
    """Contact nodes as spheres; each patch's outline and a label with its force."""
    yellow = fm.Color(r=1.0, g=0.9, b=0.1, a=1.0)
    spheres = [
        fm.SpherePrimitive(
            pose=_pose(fm, V[i]), size=fm.Vector3(x=0.002, y=0.002, z=0.002), color=yellow
        )
        for i in np.flatnonzero(C)
    ]
    texts = [
        fm.TextPrimitive(
            pose=_pose(fm, np.asarray(p.centroid, dtype=np.float64) + [0.0, 0.0, 0.006]),
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            color=yellow,
            text=f"patch {k}: {float(np.linalg.norm(p.force)):.2f} N",
        )
        for k, p in enumerate(patches)
    ]
    lines = []
    for p in patches:
        seg = patch_outline(T, np.asarray(p.nodes, dtype=np.int64))
        if len(seg):
            lines.append(
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineList,
                    pose=_pose(fm, np.zeros(3)),
                    thickness=2.0,
                    scale_invariant=True,
                    points=_points(fm, V[seg.ravel()]),
                    color=yellow,
                )
            )
    return {"spheres": spheres, "texts": texts, "lines": lines}


def _wrench_arrows(
    fm: Any,
    net_force: NDArray,
    net_torque: NDArray,
    patches: list[Any] | None,
    arrow_scale: float,
    min_arrow_n: float,
    torque_scale: float,
) -> list[Any]:
    """The net force on its line of action (ending where it meets the first patch's
    centroid's foot on that line) and the torque about the origin."""
    f = np.asarray(net_force, dtype=np.float64).reshape(3)
    tau = np.asarray(net_torque, dtype=np.float64).reshape(3)
    out = []
    f2 = float(f @ f)
    if f2 > min_arrow_n**2 and np.isfinite(f2):
        axis0 = np.cross(f, tau) / f2  # the central axis' point nearest the origin
        d = f / np.sqrt(f2)
        c = np.asarray(patches[0].centroid, dtype=np.float64) if patches else axis0
        tip = axis0 + ((c - axis0) @ d) * d
        out.append(_arrow(fm, tip, f, arrow_scale, fm.Color(r=0.1, g=0.4, b=1.0, a=1.0), 0.0015))
    t_mag = float(np.linalg.norm(tau))
    if t_mag * torque_scale > 1e-4 and np.isfinite(t_mag):
        purple = fm.Color(r=0.6, g=0.2, b=0.9, a=1.0)
        out.append(_arrow(fm, tau * torque_scale, tau, torque_scale, purple, 0.0015))
    return out


def patch_outline(triangles: NDArray, nodes: NDArray) -> NDArray[np.int64]:
    """E x 2 node pairs outlining a patch: the mesh edges between two patch nodes that fewer
    than two triangles lying wholly in the patch share (its border, and the edges of a patch
    too thin to hold a triangle)."""
    T = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    inside = np.zeros(int(T.max()) + 1 if T.size else 0, bool)
    nodes = np.asarray(nodes, dtype=np.int64)
    inside[nodes[nodes < len(inside)]] = True
    if not inside.any():
        return np.zeros((0, 2), np.int64)
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    full = np.tile(inside[T].all(axis=1), 3)
    keep = inside[e].all(axis=1)
    e, full = np.sort(e[keep], axis=1), full[keep]
    if not len(e):
        return np.zeros((0, 2), np.int64)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    shared = np.bincount(inv.ravel(), weights=full.astype(float), minlength=len(edges))
    return np.asarray(edges[shared < 2], dtype=np.int64)


def net_force_payload(f: NDArray, t_ns: int, frame_index: int = 0) -> dict[str, Any]:
    v = np.asarray(f, dtype=np.float64).reshape(3)
    return {
        "timestamp": _stamp(t_ns),
        "frame_index": int(frame_index),
        "x": float(v[0]),
        "y": float(v[1]),
        "z": float(v[2]),
        "magnitude": float(np.linalg.norm(v)),
    }


def jpeg_image(rgb: NDArray, t_ns: int, quality: int = 80) -> Any:
    """A foxglove.CompressedImage (JPEG) of an RGB uint8 image."""
    import cv2
    import foxglove.messages as fm

    ok, buf = cv2.imencode(
        ".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:
        raise ValueError("JPEG encoding failed")
    return fm.CompressedImage(
        timestamp=fm.Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000)),
        frame_id=FRAME_ID,
        data=buf.tobytes(),
        format="jpeg",
    )


class SceneBuilder:
    """Force frames (``bubble_rt.v1`` ForceFrame + Mesh messages) -> Foxglove messages."""

    def __init__(
        self,
        arrow_scale: float = ARROW_SCALE_M_PER_N,
        pressure_max_pa: float = PRESSURE_MAX_PA,
        image_hz: float = 10.0,
        arrows_for: str = "contact",
    ) -> None:
        if arrows_for not in ("contact", "all"):
            raise ValueError(f"arrows_for must be 'contact' or 'all', got {arrows_for!r}")
        self.arrows_for = arrows_for
        self.arrow_scale = arrow_scale
        self.pressure_max_pa = pressure_max_pa
        self.image_period = 1.0 / image_hz if image_hz > 0 else float("inf")
        self._last_image = -float("inf")
        self._mesh_id = ""
        self._mesh: Any = None

    def frame(self, force_msg: Any, mesh_msg: Any, frame: Any = None) -> list[Encoded]:
        """Scene, net force, true force (sim frames) and image (rate-limited) of one frame;
        the mesh is drawn at its measured shape (the frame's node_displacements, if any)."""
        from bubble_rt.io import protocol

        if mesh_msg is not None and mesh_msg.mesh_id != self._mesh_id:
            self._mesh = protocol.decode_mesh(mesh_msg)
            self._mesh_id = mesh_msg.mesh_id
        if self._mesh is None:
            return []
        d = protocol.decode_force_frame(force_msg)
        t_ns = int(d.capture_time_ns)
        verts = np.asarray(self._mesh.vertices, dtype=np.float64)
        if d.node_displacements is not None and d.node_displacements.shape == verts.shape:
            verts = verts + np.nan_to_num(d.node_displacements)
        scene = scene_update(
            verts,
            self._mesh.triangles,
            d.node_forces,
            d.normal_pressure,
            d.contact,
            d.patches,
            boundary=self._mesh.boundary,
            arrows_for=self.arrows_for,
            t_ns=t_ns,
            arrow_scale=self.arrow_scale,
            pressure_max_pa=self.pressure_max_pa,
            net_force=d.net_force if d.net_torque is not None else None,
            net_torque=d.net_torque,
        )
        out = [
            _proto(TOPIC_SCENE, scene, t_ns),
            _json(
                TOPIC_NET_FORCE,
                NET_FORCE_SCHEMA,
                net_force_payload(d.net_force, t_ns, d.frame_index),
                t_ns,
            ),
        ]
        truth = getattr(frame, "truth", None) if frame is not None else None
        if truth is not None and getattr(truth, "net_force", None) is not None:
            out.append(
                _json(
                    TOPIC_TRUE_FORCE,
                    NET_FORCE_SCHEMA,
                    net_force_payload(truth.net_force, t_ns, d.frame_index),
                    t_ns,
                )
            )
        rgb = getattr(frame, "rgb", None) if frame is not None else None
        now = time.monotonic()
        if rgb is not None and now - self._last_image >= self.image_period:
            self._last_image = now
            out.append(_proto(TOPIC_IMAGE, jpeg_image(rgb, t_ns), t_ns))
        return out

    @staticmethod
    def status(msg: Any) -> Encoded:
        from bubble_rt.io.protocol import pb

        t_ns = int(msg.time_ns)
        payload = {
            "timestamp": _stamp(t_ns),
            "state": pb.Status.State.Name(msg.state),
            "reason": msg.reason,
            "frame_rate_hz": float(msg.frame_rate_hz),
            "frames_published": int(msg.frames_published),
            "frames_dropped": int(msg.frames_dropped),
            "latency_p50_ms": float(msg.latency.p50_ms),
            "latency_p99_ms": float(msg.latency.p99_ms),
        }
        return _json(TOPIC_STATUS, STATUS_SCHEMA, payload, t_ns)


def channel_specs() -> list[Encoded]:
    """Every channel (topic and schema, empty data) so that clients see them all at once."""
    import foxglove.messages as fm

    out = []
    for topic, cls in ((TOPIC_SCENE, fm.SceneUpdate), (TOPIC_IMAGE, fm.CompressedImage)):
        s = cls.get_schema()
        out.append(Encoded(topic, s.name, s.encoding, bytes(s.data), "protobuf", b"", 0))
    for topic, schema in (
        (TOPIC_NET_FORCE, NET_FORCE_SCHEMA),
        (TOPIC_TRUE_FORCE, NET_FORCE_SCHEMA),
        (TOPIC_STATUS, STATUS_SCHEMA),
    ):
        out.append(_json(topic, schema, {}, 0))
    return out


def parse_address(address: str | None, name: str = "--foxglove") -> tuple[str, int]:
    """(host, port) of ``ws://HOST:PORT`` (or ``HOST:PORT``, or ``:PORT``).

    The port is 1-65535, or ``*`` for any free port (returned as 0, as ZeroMQ's ``:*``).
    Raises ValueError naming ``name`` (the option the address came from).
    """
    from bubble_rt._validate import port_problem

    a = address or DEFAULT_ADDRESS
    if "//" not in a:
        a = "ws://" + a
    any_port = a.endswith(":*")
    u = urlparse(a[:-2] if any_port else a)
    if u.scheme not in ("ws", ""):
        raise ValueError(f"{name} {address!r}: only ws://HOST:PORT is served")
    host = u.hostname or "127.0.0.1"
    if any_port:
        return host, 0
    _, colon, port = u.netloc.rpartition(":")
    if not colon or "]" in port:  # no port (an IPv6 host's colons end with "]")
        return host, 8765
    problem = port_problem(port)
    if problem is not None:
        raise ValueError(f"{name} {address!r}: {problem} (use :* for any free port)")
    return host, int(port)
