"""Rigid indenters as signed distance functions (SDF), vectorised NumPy.

Every indenter is described in its own frame ("indenter frame", metres). The presets put the
contact tip (lowest point) at the origin with the body rising along +z, so an indenter posed
with an identity rotation above the dome presses along -z. A pose is the 4 x 4 rigid transform
indenter -> mesh frame.

Protocol used by the physics: ``distance(points, pose) -> (d, grad)`` with points M x 3 in the
mesh frame, d (M,) the signed distance in metres (negative inside the indenter) and grad M x 3
its gradient (unit outward normal of the nearest surface point) in the mesh frame.

The paper's five indenters (sizes chosen here, documented in ``PRESET_SIZES``):
- "round": sphere, radius 10 mm.
- "point": a pin, capsule of radius 3 mm (hemispherical tip), 20 mm long.
- "line": a horizontal rod along x, capsule of radius 4 mm, 40 mm long (cylinder part).
- "square": box with a 20 mm x 20 mm face, 20 mm tall, edges rounded with radius 2 mm.
- "split": two vertical pins (capsules of radius 4 mm, 20 mm long) 25 mm apart along x.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "Indenter",
    "Shape",
    "Sphere",
    "Capsule",
    "Box",
    "Union",
    "PRESET_SIZES",
    "preset",
    "from_spec",
]

Array = NDArray[np.float64]


@runtime_checkable
class Indenter(Protocol):
    """Anything the physics can press with."""

    def distance(self, points: Array, pose: Array) -> tuple[Array, Array]:
        """Signed distance (M,) m and its gradient (M x 3) of mesh-frame points M x 3."""
        ...


def _as_points(points: ArrayLike) -> Array:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be M x 3, got shape {p.shape}")
    return p


def _as_pose(pose: ArrayLike) -> Array:
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite 4 x 4 transform, got shape {T.shape}")
    return T


def _vec3(v: ArrayLike, name: str) -> Array:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


def _unit(v: Array) -> Array:
    """Rows normalised; zero rows become +z (any unit vector is a valid subgradient there)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    out = np.where(n > 1e-15, v / np.maximum(n, 1e-300), 0.0)
    out[n[:, 0] <= 1e-15] = (0.0, 0.0, 1.0)
    return out


class Shape:
    """Base: subclasses implement ``local_distance`` in the indenter frame."""

    def local_distance(self, p: Array) -> tuple[Array, Array]:
        raise NotImplementedError

    def distance(self, points: ArrayLike, pose: ArrayLike) -> tuple[Array, Array]:
        """Signed distance (M,) m and gradient (M x 3) of mesh-frame points (M x 3)."""
        p = _as_points(points)
        T = _as_pose(pose)
        R, t = T[:3, :3], T[:3, 3]
        local = (p - t) @ R  # R^T (p - t) row-wise
        d, g = self.local_distance(local)
        return d, g @ R.T

    def __or__(self, other: Shape) -> Union:
        return Union((self, other))


@dataclass(frozen=True)
class Sphere(Shape):
    """Sphere of ``radius`` (m) centred at ``center`` (indenter frame, m)."""

    radius: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise ValueError(f"sphere radius must be positive, got {self.radius}")
        object.__setattr__(self, "center", tuple(_vec3(self.center, "center")))

    def local_distance(self, p: Array) -> tuple[Array, Array]:
        v = p - np.asarray(self.center)
        r = np.linalg.norm(v, axis=1)
        return r - self.radius, _unit(v)


@dataclass(frozen=True)
class Capsule(Shape):
    """All points within ``radius`` (m) of the segment from ``a`` to ``b`` (indenter frame)."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise ValueError(f"capsule radius must be positive, got {self.radius}")
        object.__setattr__(self, "a", tuple(_vec3(self.a, "a")))
        object.__setattr__(self, "b", tuple(_vec3(self.b, "b")))

    def local_distance(self, p: Array) -> tuple[Array, Array]:
        a = np.asarray(self.a)
        ab = np.asarray(self.b) - a
        L2 = float(ab @ ab)
        s = np.clip(((p - a) @ ab) / L2, 0.0, 1.0) if L2 > 0 else np.zeros(len(p))
        v = p - (a + s[:, None] * ab)
        r = np.linalg.norm(v, axis=1)
        return r - self.radius, _unit(v)


@dataclass(frozen=True)
class Box(Shape):
    """Box with ``half_extents`` (m) centred at ``center``, edges rounded with ``rounding`` (m).

    The rounding is taken from inside: the outer size stays ``2 * half_extents``.
    """

    half_extents: tuple[float, float, float]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rounding: float = 0.0

    def __post_init__(self) -> None:
        h = _vec3(self.half_extents, "half_extents")
        if not np.all(h > 0):
            raise ValueError(f"box half extents must be positive, got {self.half_extents}")
        if not 0 <= self.rounding < h.min():
            raise ValueError(f"rounding must be in [0, min half extent), got {self.rounding}")
        object.__setattr__(self, "half_extents", tuple(h))
        object.__setattr__(self, "center", tuple(_vec3(self.center, "center")))

    def local_distance(self, p: Array) -> tuple[Array, Array]:
        v = p - np.asarray(self.center)
        sgn = np.where(v < 0, -1.0, 1.0)
        q = np.abs(v) - (np.asarray(self.half_extents) - self.rounding)
        qp = np.maximum(q, 0.0)
        out_len = np.linalg.norm(qp, axis=1)
        qmax = q.max(axis=1)
        d = out_len + np.minimum(qmax, 0.0) - self.rounding
        outside = qmax > 0
        g = np.zeros_like(v)
        g[outside] = qp[outside] / out_len[outside, None]
        k = np.argmax(q[~outside], axis=1)
        gi = np.zeros((len(k), 3))
        gi[np.arange(len(k)), k] = 1.0
        g[~outside] = gi
        return d, g * sgn


@dataclass(frozen=True)
class Union(Shape):
    """Union of shapes (the nearest one decides distance and gradient)."""

    shapes: tuple[Shape, ...]

    def __post_init__(self) -> None:
        if len(self.shapes) == 0:
            raise ValueError("a union needs at least one shape")
        object.__setattr__(self, "shapes", tuple(self.shapes))

    def local_distance(self, p: Array) -> tuple[Array, Array]:
        ds, gs = zip(*(s.local_distance(p) for s in self.shapes), strict=True)
        D = np.stack(ds)
        k = np.argmin(D, axis=0)
        idx = np.arange(len(p))
        return D[k, idx], np.stack(gs)[k, idx]


#: Sizes (metres) of the paper's five indenters as modelled here.
PRESET_SIZES: dict[str, dict[str, float]] = {
    "round": {"radius": 0.010},
    "point": {"radius": 0.003, "length": 0.020},
    "line": {"radius": 0.004, "length": 0.040},
    "square": {"side": 0.020, "height": 0.020, "rounding": 0.002},
    "split": {"radius": 0.004, "length": 0.020, "spacing": 0.025},
}


def preset(name: str) -> Shape:
    """One of the paper's indenters: "round", "point", "line", "square", "split".

    Tip (lowest point) at the indenter-frame origin, body along +z (see module docstring).
    """
    s = PRESET_SIZES.get(name)
    if s is None:
        raise ValueError(f"unknown indenter {name!r}; choose one of {sorted(PRESET_SIZES)}")
    if name == "round":
        return Sphere(s["radius"], (0.0, 0.0, s["radius"]))
    if name == "point":
        r = s["radius"]
        return Capsule((0.0, 0.0, r), (0.0, 0.0, r + s["length"]), r)
    if name == "line":
        r, h = s["radius"], s["length"] / 2
        return Capsule((-h, 0.0, r), (h, 0.0, r), r)
    if name == "square":
        a, ht = s["side"] / 2, s["height"] / 2
        return Box((a, a, ht), (0.0, 0.0, ht), s["rounding"])
    r, L, c = s["radius"], s["length"], s["spacing"] / 2
    return Union(
        (
            Capsule((-c, 0.0, r), (-c, 0.0, r + L), r),
            Capsule((c, 0.0, r), (c, 0.0, r + L), r),
        )
    )


def from_spec(spec: str | Mapping[str, Any]) -> Shape:
    """An indenter from a preset name or a mapping (e.g. a scene's TOML table).

    Mapping forms (lengths in metres): {"type": "sphere", "radius", "center"?},
    {"type": "capsule", "a", "b", "radius"} or {"type": "capsule", "radius", "length",
    "center"?, "axis"? (default +z)}, {"type": "box", "half_extents" or "size" (full
    lengths), "center"?, "rounding"?}, {"type": "union", "shapes": [spec, ...]},
    {"type": "preset", "name"}.
    """
    if isinstance(spec, str):
        return preset(spec)
    kind = str(spec.get("type", "")).lower()
    args = {k: v for k, v in spec.items() if k != "type"}
    try:
        if kind == "preset":
            return preset(str(args["name"]))
        if kind == "sphere":
            return Sphere(float(args["radius"]), tuple(args.get("center", (0.0, 0.0, 0.0))))
        if kind == "capsule":
            if "a" not in args and "length" in args:
                # Centre / axis / cylinder length form.
                c = _vec3(args.get("center", (0.0, 0.0, 0.0)), "center")
                ax = _vec3(args.get("axis", (0.0, 0.0, 1.0)), "axis")
                ax = ax / np.linalg.norm(ax)
                h = 0.5 * float(args["length"]) * ax
                return Capsule(tuple(c - h), tuple(c + h), float(args["radius"]))
            return Capsule(tuple(args["a"]), tuple(args["b"]), float(args["radius"]))
        if kind == "box":
            if "half_extents" not in args and "size" in args:
                args["half_extents"] = tuple(0.5 * _vec3(args["size"], "size"))
            return Box(
                tuple(args["half_extents"]),
                tuple(args.get("center", (0.0, 0.0, 0.0))),
                float(args.get("rounding", 0.0)),
            )
        if kind == "union":
            shapes: Sequence[Any] = args["shapes"]
            return Union(tuple(from_spec(s) for s in shapes))
    except KeyError as exc:
        raise ValueError(f"indenter spec {dict(spec)!r} lacks {exc.args[0]!r}") from exc
    raise ValueError(f"unknown indenter type {kind!r} in {dict(spec)!r}")
