"""Lifting and filling on the mesh: pixels back-projected through a hole-filled depth map, and
node values filled or checked from their neighbours over the mesh graph (docs/deformation.md).

The depth filling and the pinhole lift run in C++ (``bubble_rt._core``, cpp/depth_fill.cpp and
cpp/lifting.cpp); the graph operations are SciPy. Used by the deformation tracker and by the
mesh fitting.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.frames import FrameError
from bubble_rt.mesh import Mesh


def mesh_laplacian(mesh: Mesh) -> sp.csr_matrix:
    """Uniform graph Laplacian (N x N, D - A) of the mesh edges."""
    A = mesh.adjacency()
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (sp.diags(deg) - A).tocsr()


_DENSE_FILL_MAX = 150


def harmonic_fill(
    L: sp.csr_matrix, values: NDArray[np.float64], known: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Replace rows of ``values`` (N x k) where ``known`` is False by the harmonic interpolant
    of the known rows over the graph Laplacian ``L``. Unknown nodes cut off from every known
    node get 0 (a tiny diagonal shift keeps their block non-singular)."""
    out = np.array(values, dtype=np.float64, copy=True)
    unknown = ~known
    if not unknown.any():
        return out
    if not known.any():
        out[:] = 0.0
        return out
    iu = np.flatnonzero(unknown)
    # L[iu][:, known] @ out[known] as one product over all of L: SciPy's fancy slicing of the
    # rows and columns took most of a millisecond per frame on the 749-node mesh.
    rhs = -(L @ np.where(known[:, None], out, 0.0))[iu]
    if len(iu) <= _DENSE_FILL_MAX:
        # A few flagged nodes per frame is the usual case: a dense solve is microseconds where
        # SciPy's sparse setup costs about a millisecond.
        Luu_d = _dense_principal_block(L, iu) + 1e-9 * np.eye(len(iu))
        sol = np.linalg.solve(Luu_d, rhs.reshape(len(iu), -1))
    else:
        Luu = L[iu][:, iu] + sp.identity(len(iu), format="csr") * 1e-9
        sol = spla.spsolve(Luu.tocsc(), rhs)
    out[iu] = np.asarray(sol).reshape(len(iu), -1)
    out[~np.isfinite(out)] = 0.0
    return out


def _dense_principal_block(L: sp.csr_matrix, idx: NDArray[np.intp]) -> NDArray[np.float64]:
    """``L[idx][:, idx]`` as a dense array, read from the CSR arrays of the rows ``idx``."""
    pos = np.full(L.shape[0], -1, dtype=np.intp)
    pos[idx] = np.arange(len(idx))
    starts = L.indptr[idx]
    lens = L.indptr[idx + 1] - starts
    rows = np.repeat(np.arange(len(idx)), lens)
    flat = np.arange(int(lens.sum())) + np.repeat(starts - np.cumsum(lens) + lens, lens)
    cols = pos[L.indices[flat]]
    keep = cols >= 0
    out = np.zeros((len(idx), len(idx)))
    np.add.at(out, (rows[keep], cols[keep]), L.data[flat][keep])
    return out


def sample_z(depth: NDArray, uv: NDArray) -> NDArray[np.float64]:
    from scipy.ndimage import map_coordinates

    return map_coordinates(depth, [uv[:, 1], uv[:, 0]], order=1, mode="nearest")


def leave_one_out_residual(
    L: sp.csr_matrix, values: NDArray[np.float64], known: NDArray[np.bool_], nodes: NDArray[np.intp]
) -> NDArray[np.float64]:
    """For each of ``nodes`` (known ones), its value minus the harmonic interpolant of all the
    other known rows at it: how far it sits from what the membrane around it says (k columns
    of ``values``, N x k). Unknown nodes are eliminated (Kron reduction of ``L`` onto the known
    set), so the answer holds however many of a node's own neighbours are unmeasured; with
    every neighbour known it is the value minus the mean of the neighbours.

    Args:
        L: N x N graph Laplacian (D - A).
        values: N x k; rows of unknown nodes are ignored.
        known: N bool.
        nodes: indices (known nodes) to evaluate.

    Returns:
        len(nodes) x k residuals (0 for a node cut off from every other known node).
    """
    vals = np.asarray(values, dtype=np.float64).reshape(len(known), -1)
    nodes = np.asarray(nodes, dtype=np.intp)
    if len(nodes) == 0:
        return np.zeros((0, vals.shape[1]))
    xk = np.where(known[:, None], vals, 0.0)
    Lc = L[nodes]
    y = np.asarray(Lc @ xk)  # row c of L applied to the known values
    d = np.asarray(Lc[:, nodes].diagonal(), dtype=np.float64).copy()
    iu = np.flatnonzero(~known)
    if len(iu):
        # Eliminate the unknown nodes: L~_CK = L_CK - L_CS L_SS^-1 L_SK.
        Lcs = Lc[:, iu].toarray()
        if Lcs.any():
            Lss = L[iu][:, iu].toarray() + 1e-9 * np.eye(len(iu))
            W = np.linalg.solve(Lss, Lcs.T)  # |S| x |C|
            Lsk = L[iu]
            y -= W.T @ np.asarray(Lsk @ xk)
            d -= np.einsum("sc,sc->c", W, Lcs.T)
    out = np.zeros_like(y)
    ok = d > 1e-9
    out[ok] = y[ok] / d[ok, None]
    return out


def neighbour_table(L: sp.csr_matrix) -> NDArray[np.intp]:
    """N x max_degree neighbour indices from a Laplacian, padded with -1."""
    n = L.shape[0]
    rows = [[j for j in L.indices[L.indptr[i] : L.indptr[i + 1]] if j != i] for i in range(n)]
    width = max(len(r) for r in rows)
    out = np.full((n, width), -1, dtype=np.intp)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out


def neighbour_outliers(
    U: NDArray,
    measured: NDArray[np.bool_],
    nb: NDArray[np.intp],
    tol: float,
    relative_tol: float = 0.0,
) -> NDArray[np.bool_]:
    """Measured nodes whose U (N x 3, m) is further than ``max(tol, relative_tol * |m|)`` (m)
    from ``m``, the component-wise median of their measured neighbours (needs at least two of
    them); ``nb`` is
    ``neighbour_table``'s N x W table. C++ (cpp/neighbour_median.h): the NumPy version, a
    gather and sort of N x W x 3 values, cost a third of a millisecond per frame."""
    from bubble_rt import _core

    return np.asarray(
        _core._neighbour_outliers(
            np.ascontiguousarray(U, dtype=np.float64),
            np.ascontiguousarray(measured, dtype=bool),
            np.ascontiguousarray(nb, dtype=np.int64),
            float(tol),
            float(relative_tol),
        ),
        dtype=bool,
    )


def lift_pixels(
    depth: NDArray,
    uv: NDArray,
    camera: Camera,
    *,
    max_fill_level: int = 3,
    depth_smoothing: int = 4,
) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """Back-project pixels through a depth image: the lifting step on its own.

    Args:
        depth: H x W depth (metres of camera z, 0 / NaN invalid); holes are filled first.
        uv: N x 2 pixel coordinates (u right, v down; pixel centres at integers).
        camera: gives intrinsics and the camera -> mesh pose.

    Returns:
        Mesh-frame points (N x 3, metres; zeros where flagged) and FLAG_* bits (N uint8).
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.shape != (camera.height, camera.width):
        raise FrameError(
            f"depth shape {d.shape} differs from the camera's {camera.height} x {camera.width}"
        )
    pts, flags = lift(
        d, np.asarray(uv, dtype=np.float64).reshape(-1, 2), camera, max_fill_level, depth_smoothing
    )
    pts[flags != 0] = 0.0
    return pts, flags


def lift(
    depth: NDArray, uv: NDArray, cam: Camera, max_fill_level: int, smoothing: int
) -> tuple[NDArray, NDArray]:
    """Mesh-frame points (N x 3) of pixels through a hole-filled depth map, and flags."""
    from bubble_rt import _core

    filled, level = _core._fill_depth(
        np.ascontiguousarray(depth, dtype=np.float32), smoothing, max_fill_level + 1
    )
    pts, flags = _core._lift_pixels(
        filled,
        level,
        np.ascontiguousarray(uv, dtype=np.float64),
        cam.fx,
        cam.fy,
        cam.cx,
        cam.cy,
        max_fill_level,
    )
    flags = np.asarray(flags, dtype=np.uint8).copy()
    return lifted_points(np.asarray(pts), flags, filled, uv, cam), flags


def lifted_points(
    pinhole: NDArray, flags: NDArray, filled: NDArray | None, uv: NDArray, cam: Camera
) -> NDArray[np.float64]:
    """Mesh-frame points (N x 3) from the C++ pinhole lift's camera-frame ``pinhole`` points of
    pixels ``uv`` (N x 2); with lens distortion the sampled depths of the unflagged pixels are
    re-projected exactly through ``filled`` (the hole-filled depth, needed only then)."""
    if cam.has_distortion:
        assert filled is not None
        ok = flags == 0
        pinhole = np.zeros((len(uv), 3))
        pinhole[ok] = cam.to_camera(cam.backproject(uv[ok], sample_z(filled, uv[ok])))
    return cam.to_mesh(pinhole)
