"""Fit a reference mesh to the untouched membrane seen by the camera.

Approach (like the public implementation, which domes a flat elliptical mesh onto the reference
point cloud and evens it out):

1. The camera pose (``camera.pose``, camera -> mesh frame) places the template's footprint:
   the rim plane is z = 0 of the mesh frame. For the simulator and the default camera this is
   known; for the public Punyo recording it comes from :func:`punyo_pose` (``bubble_rt.io.punyo``).
2. Every interior node keeps its footprint position (x, y) and slides along the mesh z axis
   until it meets the observed surface: the hole-filled reference depth map, bilinear, solved
   per node by a secant iteration on ``z_cam(x, y, h) - depth(project(x, y, h))``.
3. Nodes the camera cannot see, that fall on unfillable depth, that would move further than
   ``max_offset_m`` from the template (an occluder, not the membrane), or whose height offset
   is out of line with their neighbours' (by more than ``outlier_m``) take the height offset of
   their neighbours by a Laplacian (harmonic) fill; rim nodes stay where the template has them.
4. Evening out: a few tangential smoothing steps (footprint positions move halfway to the mean
   of their neighbours, then are re-lifted), kept only while no triangle flips and the smallest
   angle does not get worse.

Node count, connectivity and rim are those of the template.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from bubble_rt.camera import Camera
from bubble_rt.estimation.deformation import Reference
from bubble_rt.estimation.lifting import (
    harmonic_fill,
    mesh_laplacian,
    neighbour_outliers,
    neighbour_table,
)
from bubble_rt.frames import FrameError
from bubble_rt.mesh import Mesh, MeshGeometry


class _Surface:
    """The reference depth surface seen by the camera (hole-filled, bilinear)."""

    def __init__(self, depth: NDArray, camera: Camera, max_fill_level: int) -> None:
        from bubble_rt import _core

        filled, level = _core._fill_depth(np.ascontiguousarray(depth, dtype=np.float32), 4)
        self.filled = np.asarray(filled, dtype=np.float64)
        self.level = np.asarray(level)
        self.camera = camera
        self.max_fill_level = max_fill_level

    def gap(self, pts: NDArray) -> tuple[NDArray, NDArray]:
        """Camera z of mesh-frame points minus the observed depth at their pixel (m), and
        whether the observation there is usable."""
        cam = self.camera
        uv, z = cam.project(pts)
        with np.errstate(invalid="ignore"):
            ok = (
                np.isfinite(uv).all(axis=1)
                & (z > 0)
                & (uv[:, 0] >= 0)
                & (uv[:, 1] >= 0)
                & (uv[:, 0] <= cam.width - 1)
                & (uv[:, 1] <= cam.height - 1)
            )
        uvc = np.where(ok[:, None], uv, 0.0)
        d = map_coordinates(self.filled, [uvc[:, 1], uvc[:, 0]], order=1, mode="nearest")
        lv = np.maximum.reduce(
            [
                self.level[
                    np.clip(np.floor(uvc[:, 1]).astype(int) + dy, 0, cam.height - 1),
                    np.clip(np.floor(uvc[:, 0]).astype(int) + dx, 0, cam.width - 1),
                ]
                for dy in (0, 1)
                for dx in (0, 1)
            ]
        )
        ok &= (lv <= self.max_fill_level) & (d > 0)
        return z - d, ok

    def lift(self, xy: NDArray, h0: NDArray, iterations: int = 25) -> tuple[NDArray, NDArray]:
        """Heights h (m) where the vertical lines through footprint points xy meet the surface."""

        def g(h: NDArray) -> tuple[NDArray, NDArray]:
            return self.gap(np.column_stack([xy, h]))

        ha = h0.astype(np.float64).copy()
        hb = ha + 2e-3
        ga, oka = g(ha)
        gb, okb = g(hb)
        ok = oka & okb
        for _ in range(iterations):
            den = gb - ga
            safe = np.abs(den) > 1e-12
            step = np.where(safe, -gb * (hb - ha) / np.where(safe, den, 1.0), 0.0)
            step = np.clip(step, -0.01, 0.01)
            ha, ga = hb, gb
            hb = hb + step
            gb, okn = g(hb)
            ok &= okn
            if np.all(np.abs(step[ok]) < 1e-8):
                break
        ok &= np.abs(gb) < 1e-5
        return hb, ok


def fit_mesh(
    template: Mesh,
    reference: Reference,
    camera: Camera,
    *,
    max_offset_m: float = 0.015,
    smoothing_steps: int = 5,
    max_fill_level: int = 5,
    outlier_m: float = 0.002,
) -> Mesh:
    """Lift ``template``'s footprint onto the reference surface seen by ``camera``.

    Args:
        template: mesh in the mesh frame (rim plane z = 0); its x, y give the footprint.
        reference: captured reference (its ``depth`` is used).
        camera: camera with the pose placing the mesh frame (camera -> mesh).
        max_offset_m: nodes whose fitted height differs from the template's by more are
            treated as unseen (occluders, background) and filled from neighbours.
        smoothing_steps: evening-out steps (0 disables).
        outlier_m: a node whose height offset differs from the median of its neighbours'
            by more than this is treated as unseen (edges of occluders, depth glitches).
        max_fill_level: depth from larger holes than about 2^level pixels is not trusted.

    Returns:
        A Mesh with the template's node count, connectivity and rim, nodes on the surface.
    """
    if reference.depth is None:
        raise FrameError("depth is missing: mesh fitting needs a reference with depth")
    if reference.depth.shape != (camera.height, camera.width):
        raise FrameError(
            f"reference depth size {reference.depth.shape[1]} x {reference.depth.shape[0]} "
            f"differs from the camera's {camera.width} x {camera.height}"
        )
    surf = _Surface(reference.depth, camera, max_fill_level)
    V0 = np.array(template.vertices, dtype=np.float64)
    rim = np.zeros(template.n_nodes, bool)
    rim[template.boundary] = True
    L = mesh_laplacian(template)
    nb = neighbour_table(L)

    def place(xy: NDArray, h_start: NDArray) -> tuple[NDArray, NDArray]:
        h, ok = surf.lift(xy, h_start)
        ok &= ~rim & (np.abs(h - V0[:, 2]) <= max_offset_m)
        off = np.where(ok, h - V0[:, 2], 0.0)
        # Occluder edges and depth glitches: heights out of line with their neighbours.
        for _ in range(3):
            bad = neighbour_outliers(np.column_stack([off, 0 * off, 0 * off]), ok, nb, outlier_m)
            if not bad.any():
                break
            ok &= ~bad
            off = np.where(ok, off, 0.0)
        off = harmonic_fill(L, off[:, None], ok | rim)[:, 0]
        off[rim] = 0.0
        return np.column_stack([xy, V0[:, 2] + off]), ok

    V, seen = place(V0[:, :2], V0[:, 2])
    if not seen.any():
        raise FrameError("depth shows no membrane where the template projects (check the pose)")
    best = template.with_vertices(V)
    best_angle = best.min_angle_deg()
    A = (L.copy() * -1.0).tolil()
    A.setdiag(0)
    A = A.tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    for _ in range(smoothing_steps):
        avg = (A @ V) / deg[:, None]
        xy = V[:, :2].copy()
        xy[~rim] = 0.5 * xy[~rim] + 0.5 * avg[~rim, :2]
        cand, _ = place(xy, V[:, 2])
        m = template.with_vertices(cand)
        if not _footprint_ccw(m) or m.min_angle_deg() < best_angle:
            break
        V, best, best_angle = cand, m, m.min_angle_deg()
    return best


def _footprint_ccw(mesh: Mesh) -> bool:
    p = mesh.vertices[mesh.triangles]
    nz = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    return bool(np.all(nz > 0))


def surface_residuals(mesh: Mesh, reference: Reference, camera: Camera) -> NDArray[np.float64]:
    """Per-node camera-z distance (m) between the mesh nodes and the observed reference
    surface at their pixel; NaN where the camera has no usable depth."""
    if reference.depth is None:
        raise FrameError("depth is missing: residuals need a reference with depth")
    surf = _Surface(reference.depth, camera, max_fill_level=0)
    g, ok = surf.gap(np.asarray(mesh.vertices))
    return np.where(ok, g, np.nan)


def dome_apex(
    depth: NDArray,
    camera: Camera,
    top_fraction: float = 0.7,
    geometry: MeshGeometry | None = None,
) -> tuple[NDArray[np.float64], float, float]:
    """Apex of the observed dome in the mesh frame, from a quadratic fit to its top.

    The points of ``depth`` (H x W, m) over the footprint (``geometry``'s ellipse, default
    MeshGeometry()) whose height exceeds ``top_fraction`` of the top height are fitted with
    z = quadratic(x, y).

    Returns:
        apex (3,) in the mesh frame (m), yaw (rad) of the dome's long axis about mesh z
        (0 when it runs along x), and the curvature ratio short/long axis (about
        (b / a)^2 for an elliptical footprint with semi-axes a > b).
    """
    P = camera.depth_to_points(np.asarray(depth))
    g = geometry or MeshGeometry()
    P = P[np.isfinite(P).all(axis=1)]
    P = P[(P[:, 0] / g.semi_axis_x) ** 2 + (P[:, 1] / g.semi_axis_y) ** 2 < 1.0]
    if len(P) < 100:
        raise FrameError("depth has too few valid points over the footprint to locate the dome")
    top = np.percentile(P[:, 2], 99.5)
    Q = P[P[:, 2] > top_fraction * top]
    x, y, z = Q.T
    A = np.column_stack([x * x, y * y, x * y, x, y, np.ones_like(x)])
    c = np.linalg.lstsq(A, z, rcond=None)[0]
    H = np.array([[2 * c[0], c[2]], [c[2], 2 * c[1]]])
    if np.any(np.linalg.eigvalsh(H) >= 0):
        raise FrameError("the observed top is not a dome (quadratic fit is not concave)")
    xy = np.linalg.solve(H, -c[3:5])
    h = float(c[5] + c[3:5] @ xy + 0.5 * xy @ H @ xy)
    w, vecs = np.linalg.eigh(H)  # ascending: most negative (strongest curvature) first
    long_axis = vecs[:, 1]
    yaw = float(np.arctan2(long_axis[1], long_axis[0]))
    yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2  # an axis, not a direction
    return np.array([xy[0], xy[1], h]), yaw, float(w[1] / w[0])


def centre_pose(camera: Camera, depth: NDArray, max_shift_m: float = 0.01) -> Camera:
    """The camera with its pose corrected in the rim plane so that the observed dome's apex
    sits over the footprint centre and its long axis along mesh x.

    Only the in-plane placement (x, y, yaw) is derived from the data; the rim plane (tilt and
    height) is kept, since the rim itself is hidden. Corrections larger than ``max_shift_m``
    or 10 degrees raise FrameError (a wrong initial pose, not a refinement).
    """
    apex, yaw, _ = dome_apex(depth, camera)
    if np.hypot(apex[0], apex[1]) > max_shift_m or abs(yaw) > np.radians(10.0):
        raise FrameError(
            f"dome apex at ({apex[0] * 1e3:.1f}, {apex[1] * 1e3:.1f}) mm, yaw "
            f"{np.degrees(yaw):.1f} deg: too far from the footprint centre for a refinement"
        )
    c, s = np.cos(-yaw), np.sin(-yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = -(T[:2, :2] @ apex[:2])
    return camera.with_pose(T @ camera.pose_matrix)
