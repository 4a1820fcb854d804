"""Exact per-pixel ray casting of a triangle mesh in NumPy (reference depth rendering)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt.reference.model import _as_mesh_arrays

if TYPE_CHECKING:
    from bubble_rt.camera import Camera


@dataclass
class RayHits:
    """Per-pixel first hit of camera rays on a triangle mesh (mesh frame, metres).

    Attributes:
        triangle: (H, W) int64 hit triangle index, -1 where the ray misses.
        bary: (H, W, 3) barycentric weights of the hit on that triangle's corners.
        distance: (H, W) distance along the unit ray from the camera centre, NaN on a miss.
        direction: (H, W, 3) unit ray directions in the mesh frame.
        depth: (H, W) camera z of the hit (the depth-image value), 0 on a miss.
    """

    triangle: NDArray[np.int64]
    bary: NDArray[np.float64]
    distance: NDArray[np.float64]
    direction: NDArray[np.float64]
    depth: NDArray[np.float64]


def raycast_mesh(vertices: ArrayLike, triangles: ArrayLike, camera: Camera) -> RayHits:
    """Cast one ray per pixel centre through ``camera`` onto a mesh (Moeller-Trumbore).

    Triangles are visited one at a time over their projected pixel bounding box, with a
    z-buffer on ray distance; exact for any pinhole camera (distortion via ``normalized``).
    """
    V, T = _as_mesh_arrays(vertices, triangles)
    H, W = camera.height, camera.width
    P = camera.pose_matrix
    origin = P[:3, 3]
    xy = camera.normalized(camera.pixel_grid())
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    dirs = (d_cam @ P[:3, :3].T).reshape(H, W, 3)
    cos_z = d_cam[:, 2].reshape(H, W)

    tri_id = np.full((H, W), -1, dtype=np.int64)
    bary = np.zeros((H, W, 3))
    dist = np.full((H, W), np.inf)
    uv, z = camera.project(V)
    eps = 1e-9
    for t_idx, (ia, ib, ic) in enumerate(T):
        if min(z[ia], z[ib], z[ic]) <= 0:
            continue
        us, vs = uv[[ia, ib, ic], 0], uv[[ia, ib, ic], 1]
        u0, u1 = max(int(np.floor(us.min())) - 1, 0), min(int(np.ceil(us.max())) + 1, W - 1)
        v0, v1 = max(int(np.floor(vs.min())) - 1, 0), min(int(np.ceil(vs.max())) + 1, H - 1)
        if u0 > u1 or v0 > v1:
            continue
        d = dirs[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3)
        a = V[ia]
        e1, e2 = V[ib] - a, V[ic] - a
        pvec = np.cross(d, e2)
        det = pvec @ e1
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - a
        b1 = (pvec @ s) * inv
        qvec = np.cross(s, e1)
        b2 = (d @ qvec) * inv
        tt = (e2 @ qvec) * inv
        hit = ok & (b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1 + eps) & (tt > 0)
        if not np.any(hit):
            continue
        sub_dist = dist[v0 : v1 + 1, u0 : u1 + 1].reshape(-1)
        better = hit & (tt < sub_dist)
        if not np.any(better):
            continue
        rr, cc = np.divmod(np.nonzero(better)[0], u1 - u0 + 1)
        rr += v0
        cc += u0
        dist[rr, cc] = tt[better]
        tri_id[rr, cc] = t_idx
        bary[rr, cc] = np.column_stack([1 - b1[better] - b2[better], b1[better], b2[better]])
    miss = tri_id < 0
    dist[miss] = np.nan
    depth = np.where(miss, 0.0, dist * cos_z)
    return RayHits(triangle=tri_id, bary=bary, distance=dist, direction=dirs, depth=depth)


def render_depth(vertices: ArrayLike, triangles: ArrayLike, camera: Camera) -> NDArray[np.float32]:
    """Depth image (H x W float32, camera z in metres, 0 = no surface) of a mesh."""
    return raycast_mesh(vertices, triangles, camera).depth.astype(np.float32)
