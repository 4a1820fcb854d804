"""Indenter poses along a scene's trajectory.

Keyframes in the surface form are relative to the untouched (inflated reference) membrane: the
indenter approaches a surface point along a direction and ``depth`` is its travel past first
touch. First touch is found by bisection on the indenter's signed distance to the reference
surface points, so it holds for every indenter shape without knowing where its origin is.
Indenter frame convention: the indenter presses along its own -z axis.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bubble_rt.sim.scene import Keyframe, TrajectorySpec

#: Signed distance (m, negative inside) of mesh-frame points (N x 3) to the indenter at a pose.
DistanceFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


@dataclass
class ReferenceSurface:
    """The untouched inflated membrane (mesh frame): vertices M x 3, triangles T x 3."""

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]

    def __post_init__(self) -> None:
        V = np.asarray(self.vertices, dtype=np.float64)
        T = np.asarray(self.triangles, dtype=np.int64)
        n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
        vn = np.zeros_like(V)
        for k in range(3):
            np.add.at(vn, T[:, k], n)
        self._normals = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        # Probe points: vertices plus edge midpoints so small indenters cannot pass unseen.
        mids = np.concatenate([(V[T[:, a]] + V[T[:, b]]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))])
        self._probe = np.vstack([V, mids])
        self._tree = cKDTree(self._probe)
        self._V, self._T = V, T

    def point_and_normal(self, xy: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Surface point above footprint point (x, y) and the outward unit normal there."""
        V, T = self._V, self._T
        x, y = float(xy[0]), float(xy[1])
        a, b, c = V[T[:, 0], :2], V[T[:, 1], :2], V[T[:, 2], :2]

        def cross2(p: NDArray, q: NDArray, r: NDArray) -> NDArray:
            return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (
                r[:, 0] - p[:, 0]
            )

        P = np.broadcast_to(np.array([x, y]), a.shape)
        area = cross2(a, b, c)
        with np.errstate(divide="ignore", invalid="ignore"):
            w0 = cross2(b, c, P) / area
            w1 = cross2(c, a, P) / area
        w2 = 1 - w0 - w1
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9) & (np.abs(area) > 0)
        if not inside.any():
            raise ValueError(f"footprint point ({x:.4f}, {y:.4f}) m is outside the membrane")
        lam = np.column_stack([w0, w1, w2])[inside]
        pts = np.einsum("ij,ijk->ik", lam, V[T[inside]])
        top = int(np.argmax(pts[:, 2]))
        n = np.einsum("j,jk->k", lam[top], self._normals[T[inside][top]])
        return pts[top], n / np.linalg.norm(n)

    def probe_points(self, centre: NDArray[np.float64], radius: float) -> NDArray[np.float64]:
        idx = self._tree.query_ball_point(centre, radius)
        return self._probe[np.asarray(idx, dtype=np.int64)] if idx else self._probe[:0]


def rotation_pressing_along(approach: NDArray[np.float64], spin_deg: float) -> NDArray:
    """3 x 3 rotation taking the indenter's -z axis to ``approach``, then spinning about it."""
    a = np.asarray(approach, dtype=np.float64)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, -1.0])
    v = np.cross(z, a)
    s, c = np.linalg.norm(v), float(z @ a)
    if s < 1e-12:
        R0 = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R0 = Rotation.from_rotvec(v / s * np.arctan2(s, c)).as_matrix()
    return np.asarray(Rotation.from_rotvec(a * np.radians(spin_deg)).as_matrix() @ R0)


def _pose(R: NDArray, t: NDArray) -> NDArray[np.float64]:
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = t
    return P


def touch_offset(
    surface: ReferenceSurface,
    distance: DistanceFn,
    point: NDArray[np.float64],
    approach: NDArray[np.float64],
    R: NDArray[np.float64],
    reach: float = 0.06,
) -> float:
    """How far back along -approach the indenter origin sits (from ``point``) at first touch."""
    probe = surface.probe_points(point, reach)
    if len(probe) == 0:
        probe = surface.probe_points(point, 10 * reach)

    def gap(lam: float) -> float:
        return float(np.min(distance(probe, _pose(R, point - lam * approach))))

    # Sphere tracing from outside: the signed distance bounds how far the indenter can move
    # without touching, so stepping by it never passes through the membrane.
    lam = reach
    for _ in range(40):
        g = gap(lam)
        if g > 0:
            break
        lam *= 2.0
    else:
        raise ValueError("the indenter intersects the membrane even far from the surface")
    for _ in range(500):
        g = gap(lam)
        if g < 1e-8:
            break
        lam -= g
    return lam


def _interp_keyframes(kfs: tuple[Keyframe, ...], t: float) -> Keyframe:
    if t <= kfs[0].t:
        return kfs[0]
    if t >= kfs[-1].t:
        return kfs[-1]
    i = int(np.searchsorted([k.t for k in kfs], t, side="right")) - 1
    k0, k1 = kfs[i], kfs[i + 1]
    s = (t - k0.t) / (k1.t - k0.t)

    def lerp(a: tuple | None, b: tuple | None) -> tuple | None:
        if a is None or b is None:
            return None if a is None and b is None else (a if b is None else b)
        return tuple((1 - s) * np.asarray(a) + s * np.asarray(b))

    if k0.at is not None:
        return Keyframe(
            t=t,
            at=lerp(k0.at, k1.at),
            depth=(1 - s) * k0.depth + s * k1.depth,
            approach=lerp(k0.approach, k1.approach),
            spin_deg=(1 - s) * k0.spin_deg + s * k1.spin_deg,
        )
    r = Rotation.from_rotvec([k0.rotvec, k1.rotvec])
    from scipy.spatial.transform import Slerp

    rv = Slerp([0.0, 1.0], r)([s]).as_rotvec()[0]
    return Keyframe(t=t, position=lerp(k0.position, k1.position), rotvec=tuple(rv))


def frame_times(spec: TrajectorySpec, frames: int, camera_hz: float) -> NDArray[np.float64]:
    """Trajectory time of each camera frame (s); a looping trajectory wraps around."""
    t = np.arange(frames) / camera_hz
    t_end = spec.keyframes[-1].t
    if spec.loop and t_end > 0:
        t = np.mod(t, t_end)
    return t


def keyframe_pose(
    kf: Keyframe, surface: ReferenceSurface | None, distance: DistanceFn | None
) -> NDArray[np.float64]:
    """4 x 4 indenter-to-mesh pose of one (interpolated) keyframe."""
    if kf.position is not None:
        return _pose(Rotation.from_rotvec(kf.rotvec).as_matrix(), np.asarray(kf.position))
    if surface is None or distance is None:
        raise ValueError("surface-form keyframes need the reference surface and the indenter")
    p, n = surface.point_and_normal(np.asarray(kf.at))
    a = -n if kf.approach is None else np.asarray(kf.approach, dtype=np.float64)
    a = a / np.linalg.norm(a)
    R = rotation_pressing_along(a, kf.spin_deg)
    lam0 = touch_offset(surface, distance, p, a, R)
    return _pose(R, p - (lam0 - kf.depth) * a)


def trajectory_poses(
    spec: TrajectorySpec,
    frames: int,
    camera_hz: float,
    surface: ReferenceSurface | None = None,
    distance: DistanceFn | None = None,
) -> NDArray[np.float64]:
    """Indenter poses (frames x 4 x 4) at each camera frame."""
    times = frame_times(spec, frames, camera_hz)
    return np.stack(
        [keyframe_pose(_interp_keyframes(spec.keyframes, t), surface, distance) for t in times]
    )
