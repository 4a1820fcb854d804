"""Paper-faithful reference implementation (NumPy / SciPy / CVXPY), independent of the C++ core.

This module restates method.md sections 2 and 3 (and the public implementation's deformation
pipeline) in plain Python so that the fast path can be tested and benchmarked against it. It
shares no code with ``bubble_rt._core``, ``membrane``, ``solver`` or ``estimator``; it takes
plain arrays (a ``Mesh``'s ``vertices``, ``triangles``, ``boundary``) and the shared ``Camera``.

Units: metres, newtons, pascals. Displacements and forces are N x 3 arrays, node-major; the
stiffness matrix uses the degree-of-freedom order ``[x0, y0, z0, x1, y1, z1, ...]``.

Sign convention (method.md section 2): ``F_ext = K U - dp a n`` is the force the environment
applies on each node; ``p = -n . F_ext / a`` is the inward normal pressure.

Everything here is single-threaded by intent (CVXPY + Clarabel, SciPy); set
``OPENBLAS_NUM_THREADS=1`` when timing it so the comparison with the C++ path is fair.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from bubble_rt.camera import Camera

__all__ = [
    "stiffness_matrix",
    "lumped_areas",
    "vertex_normals",
    "external_forces",
    "normal_pressure",
    "contact_mask",
    "net_force",
    "lasso_weights",
    "GroupLassoProblem",
    "RayHits",
    "raycast_mesh",
    "render_depth",
    "ReferenceSettings",
    "ReferencePipeline",
]


# --------------------------------------------------------------------------- membrane model
def _as_mesh_arrays(
    vertices: ArrayLike, triangles: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must be N x 3, got shape {V.shape}")
    if T.ndim != 2 or T.shape[1] != 3:
        raise ValueError(f"triangles must be T x 3, got shape {T.shape}")
    if T.size and (T.min() < 0 or T.max() >= len(V)):
        raise ValueError("triangles reference vertices out of range")
    return V, T


def _triangle_frames(
    V: NDArray[np.float64], T: NDArray[np.int64]
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Per triangle: i_hat, j_hat (T x 3 each), area (T,), local 2D corner coords x, y (T x 3)."""
    o, p, q = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    e1, e2 = p - o, q - o
    cr = np.cross(e1, e2)
    area2 = np.linalg.norm(cr, axis=1)
    if np.any(area2 <= 0):
        bad = int(np.argmin(area2))
        raise ValueError(f"triangle {bad} is degenerate (zero area)")
    k = cr / area2[:, None]
    len1 = np.linalg.norm(e1, axis=1)
    i_hat = e1 / len1[:, None]
    j_hat = np.cross(k, i_hat)
    x = np.column_stack([np.zeros(len(T)), len1, np.einsum("ij,ij->i", e2, i_hat)])
    y = np.column_stack([np.zeros(len(T)), np.zeros(len(T)), np.einsum("ij,ij->i", e2, j_hat)])
    return i_hat, j_hat, 0.5 * area2, x, y


def stiffness_matrix(
    vertices: ArrayLike, triangles: ArrayLike, E: float, nu: float, thickness: float
) -> sp.csr_matrix:
    """Assembled CST plane-stress stiffness K (3N x 3N, N/m, csr), method.md section 2.

    Each triangle gets an orthonormal in-plane frame (i_hat along its first edge, j_hat =
    k_hat x i_hat); ``K_e(2D) = t A B^T D B`` and ``K_e(3D) = R^T K_e(2D) R`` with
    ``R = blockdiag([i_hat j_hat]^T)``. Degree-of-freedom order is node-major.
    """
    V, T = _as_mesh_arrays(vertices, triangles)
    if not (E > 0 and thickness > 0 and -1.0 < nu < 0.5 + 1e-12):
        raise ValueError(f"invalid material E={E}, nu={nu}, thickness={thickness}")
    n = len(V)
    i_hat, j_hat, area, x, y = _triangle_frames(V, T)
    # CST shape-function derivatives: b_m = y_{m+1} - y_{m+2}, c_m = x_{m+2} - x_{m+1}.
    b = np.column_stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]])
    c = np.column_stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]])
    nt = len(T)
    B = np.zeros((nt, 3, 6))
    B[:, 0, 0::2] = b
    B[:, 1, 1::2] = c
    B[:, 2, 0::2] = c
    B[:, 2, 1::2] = b
    B /= (2.0 * area)[:, None, None]
    D = E / (1.0 - nu**2) * np.array([[1.0, nu, 0.0], [nu, 1.0, 0.0], [0.0, 0.0, (1.0 - nu) / 2]])
    K2 = np.einsum("t,tai,ab,tbj->tij", thickness * area, B, D, B)
    R = np.zeros((nt, 6, 9))
    for m in range(3):
        R[:, 2 * m, 3 * m : 3 * m + 3] = i_hat
        R[:, 2 * m + 1, 3 * m : 3 * m + 3] = j_hat
    K3 = np.einsum("tai,tab,tbj->tij", R, K2, R)
    dofs = (3 * T[:, :, None] + np.arange(3)[None, None, :]).reshape(nt, 9)
    rows = np.repeat(dofs, 9, axis=1).ravel()
    cols = np.tile(dofs, (1, 9)).ravel()
    K = sp.coo_matrix((K3.ravel(), (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    K.sum_duplicates()
    # Exact symmetry (the einsum is symmetric up to rounding).
    return sp.csr_matrix(0.5 * (K + K.T))


def lumped_areas(vertices: ArrayLike, triangles: ArrayLike) -> NDArray[np.float64]:
    """Lumped node areas a_i (N,), m^2: one third of every incident triangle's area."""
    V, T = _as_mesh_arrays(vertices, triangles)
    area = 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1)
    a = np.zeros(len(V))
    np.add.at(a, T.ravel(), np.repeat(area / 3.0, 3))
    return a


def vertex_normals(vertices: ArrayLike, triangles: ArrayLike) -> NDArray[np.float64]:
    """Area-weighted outward unit normals (N x 3); outward = the triangles' winding."""
    V, T = _as_mesh_arrays(vertices, triangles)
    cr = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])  # |cr| = 2 * area
    nsum = np.zeros_like(V)
    for m in range(3):
        np.add.at(nsum, T[:, m], cr)
    norm = np.linalg.norm(nsum, axis=1)
    norm[norm == 0] = 1.0
    return nsum / norm[:, None]  # type: ignore[no-any-return]


def external_forces(
    K: sp.spmatrix, U: ArrayLike, dp: float, areas: ArrayLike, normals: ArrayLike
) -> NDArray[np.float64]:
    """Contact forces F_ext = K U - dp a n (N x 3, newtons) for displacements U (N x 3, m)."""
    U = np.asarray(U, dtype=np.float64)
    a = np.asarray(areas, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    return (K @ U.reshape(-1)).reshape(-1, 3) - float(dp) * a[:, None] * n  # type: ignore[no-any-return]


def normal_pressure(F: ArrayLike, areas: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Inward normal pressure p_i = -n_i . F_i / a_i (N,), Pa."""
    F = np.asarray(F, dtype=np.float64)
    return -np.einsum("ij,ij->i", F, np.asarray(normals)) / np.asarray(areas)  # type: ignore[no-any-return]


def contact_mask(
    normal_pressure: ArrayLike,
    areas: ArrayLike,
    k_const: float = 2000.0,
    k_linear: float = 2.0,
) -> NDArray[np.bool_]:
    """Contact nodes: ``p_v > max(k_const, k_linear * (a . p) / sum(a))`` (method.md sec. 2)."""
    p = np.asarray(normal_pressure, dtype=np.float64)
    a = np.asarray(areas, dtype=np.float64)
    thresh = max(k_const, k_linear * float(a @ p) / float(a.sum()))
    return p > thresh  # type: ignore[no-any-return]


def net_force(F: ArrayLike, boundary: ArrayLike) -> NDArray[np.float64]:
    """Net contact force (3,), N: F summed over the non-rim nodes."""
    F = np.asarray(F, dtype=np.float64)
    keep = np.ones(len(F), dtype=bool)
    keep[np.asarray(boundary, dtype=np.int64)] = False
    return F[keep].sum(axis=0)  # type: ignore[no-any-return]


def lasso_weights(n_nodes: int, boundary: ArrayLike, k_f: float) -> NDArray[np.float64]:
    """Group-lasso force weights w_i (N,): k_f |dM| / N on the rim, k_f elsewhere."""
    b = np.asarray(boundary, dtype=np.int64)
    w = np.full(n_nodes, float(k_f))
    w[b] = k_f * len(b) / n_nodes
    return w


# --------------------------------------------------------------------------- group lasso
class GroupLassoProblem:
    """Method.md section 3 as a CVXPY problem, built once, solved with Clarabel.

        minimise  sum_i w_i ||F_ext(U + dU, dp)_i||_2 + (k_u / N) sum_i ||dU_i||^2
        s.t.      (U + dU)_i = 0 for i in the rim

    The rim constraint is exact: rim corrections are eliminated (dU_rim = -U_rim) and only the
    interior corrections are variables. U and dp are ``cp.Parameter``s, so a new frame costs
    only CVXPY's parameter update plus the Clarabel solve (no re-canonicalisation). The
    variable is kept in millimetres internally so that Clarabel sees well-scaled data.

    Single-threaded (Clarabel); set ``OPENBLAS_NUM_THREADS=1`` in benchmarks.
    """

    _VAR_SCALE = 1e-3  # metres per internal variable unit (millimetres)

    def __init__(
        self,
        vertices: ArrayLike,
        triangles: ArrayLike,
        boundary: ArrayLike,
        E: float = 1.317e6,
        nu: float = 0.5,
        thickness: float = 0.65e-3,
        k_f: float = 0.3322,
        k_u: float = 537592.0,
    ) -> None:
        import cvxpy as cp

        V, T = _as_mesh_arrays(vertices, triangles)
        self.n = n = len(V)
        self.boundary = np.unique(np.asarray(boundary, dtype=np.int64))
        self.interior = np.setdiff1d(np.arange(n), self.boundary)
        self.K = stiffness_matrix(V, T, E, nu, thickness)
        self.areas = lumped_areas(V, T)
        self.normals = vertex_normals(V, T)
        self.k_f = float(k_f)
        self.k_u = float(k_u)
        self.weights = lasso_weights(n, self.boundary, k_f)
        ni = len(self.interior)
        idof = (3 * self.interior[:, None] + np.arange(3)).ravel()
        self._idof = idof
        K_I = sp.csc_matrix(self.K[:, idof])
        an = (self.areas[:, None] * self.normals).ravel()

        self._U_int = cp.Parameter(3 * ni, name="U_interior")
        self._dp = cp.Parameter(name="dp")
        self._x = cp.Variable(3 * ni, name="dU_interior_mm")
        s = self._VAR_SCALE
        F = K_I @ self._U_int + (K_I * s) @ self._x - self._dp * an
        norms = cp.norm(cp.reshape(F, (n, 3), order="C"), 2, axis=1)
        objective = self.weights @ norms + (self.k_u / n * s * s) * cp.sum_squares(self._x)
        self._problem = cp.Problem(cp.Minimize(objective))
        self.last_status: str = ""
        self.last_solve_ms: float = float("nan")

    def _check(self, U: ArrayLike, dp: float) -> NDArray[np.float64]:
        U = np.asarray(U, dtype=np.float64)
        if U.shape != (self.n, 3):
            raise ValueError(f"U must be {self.n} x 3, got {U.shape}")
        if not (np.all(np.isfinite(U)) and np.isfinite(dp)):
            raise ValueError("U and dp must be finite")
        return U

    def solve(self, U: ArrayLike, dp: float, tight: bool = False) -> tuple[NDArray, float]:
        """Optimal correction dU (N x 3, m; rim rows = -U_rim) and the optimal objective.

        ``tight=True`` asks Clarabel for ~1e-10 tolerances (ground truth for tests);
        otherwise Clarabel's defaults are used (what the benchmark times).
        """
        import cvxpy as cp

        U = self._check(U, dp)
        self._U_int.value = U[self.interior].ravel()
        self._dp.value = float(dp)
        opts: dict[str, Any] = {}
        if tight:
            opts = dict(
                tol_gap_abs=1e-10,
                tol_gap_rel=1e-10,
                tol_feas=1e-10,
                tol_ktratio=1e-8,
                max_iter=400,
            )
        t0 = time.perf_counter()
        self._problem.solve(solver=cp.CLARABEL, warm_start=False, **opts)
        self.last_solve_ms = 1e3 * (time.perf_counter() - t0)
        self.last_status = str(self._problem.status)
        x = self._x.value
        if x is None:
            raise RuntimeError(f"reference solve failed: status {self._problem.status}")
        dU = np.zeros((self.n, 3))
        dU[self.interior] = np.asarray(x).reshape(-1, 3) * self._VAR_SCALE
        dU[self.boundary] = -U[self.boundary]
        return dU, self.objective(dU, U, dp)

    def forces(self, U: ArrayLike, dp: float) -> NDArray[np.float64]:
        """F_ext(U, dp) (N x 3, newtons) with this problem's K, areas and normals."""
        return external_forces(self.K, U, dp, self.areas, self.normals)

    def objective(self, dU: ArrayLike, U: ArrayLike, dp: float) -> float:
        """Objective of any candidate dU (N x 3, m), evaluated in NumPy (for objective gaps).

        The rim constraint is not checked here; use ``rim_violation`` for that.
        """
        dU = np.asarray(dU, dtype=np.float64).reshape(self.n, 3)
        U = np.asarray(U, dtype=np.float64).reshape(self.n, 3)
        F = self.forces(U + dU, dp)
        return float(
            self.weights @ np.linalg.norm(F, axis=1) + self.k_u / self.n * float(np.sum(dU * dU))
        )

    def rim_violation(self, dU: ArrayLike, U: ArrayLike) -> float:
        """max |U + dU| over rim nodes (m); 0 for a feasible candidate."""
        Z = np.asarray(U)[self.boundary] + np.asarray(dU)[self.boundary]
        return float(np.max(np.abs(Z))) if Z.size else 0.0


# --------------------------------------------------------------------------- ray casting
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


# --------------------------------------------------------------------------- full pipeline
@dataclass(frozen=True)
class ReferenceSettings:
    """Settings of the paper's per-frame pipeline (public implementation's values).

    Farneback: pyr_scale 0.5, levels 30, winsize 50, iterations 5, poly_n 7, poly_sigma 1.5,
    Gaussian window, grey image. Point-cloud filter: keep points whose mesh-frame height above
    the mesh's lowest point (the rim plane) is in [-z_tol, max_height + z_tol] (m) and drop statistical outliers (mean distance to ``outlier_neighbors``
    neighbours above mean + ``outlier_std_ratio`` std; the public code uses Open3D with 200
    neighbours; 0 disables). ``cloud_stride`` subsamples the depth image before lifting
    (1 = every pixel, as the public code; larger = faster Delaunay in griddata).
    ``subtract_reference_lift``: U = S_cur(P(x)+F) - S_ref(P(x)) instead of S_cur(...) - x, so a
    mesh that does not lie exactly on the reference depth surface adds no bias (equal when it does).
    """

    pyr_scale: float = 0.5
    levels: int = 30
    winsize: int = 50
    iterations: int = 5
    poly_n: int = 7
    poly_sigma: float = 1.5
    max_height: float = 0.045
    z_tol: float = 0.002
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 3.0
    cloud_stride: int = 2
    subtract_reference_lift: bool = True
    tight: bool = False


class ReferencePipeline:
    """The paper's full per-frame pipeline: Farneback flow, griddata lifting, CVXPY solve.

    Args:
        vertices, triangles, boundary: the reference mesh (mesh frame, metres).
        camera: ``bubble_rt.camera.Camera`` (pose camera -> mesh).
        reference_rgb: H x W x 3 uint8 RGB of the untouched membrane.
        reference_depth: H x W float32 camera-z depth (m), 0 invalid.
        reference_pressure_pa: pressure of the reference (Pa).
        E, nu, thickness, k_f, k_u, k_const, k_linear: model and contact constants.
    """

    def __init__(
        self,
        vertices: ArrayLike,
        triangles: ArrayLike,
        boundary: ArrayLike,
        camera: Camera,
        reference_rgb: NDArray[np.uint8],
        reference_depth: NDArray[np.floating],
        reference_pressure_pa: float,
        E: float = 1.317e6,
        nu: float = 0.5,
        thickness: float = 0.65e-3,
        k_f: float = 0.3322,
        k_u: float = 537592.0,
        k_const: float = 2000.0,
        k_linear: float = 2.0,
        settings: ReferenceSettings | None = None,
    ) -> None:
        import cv2

        self.settings = settings or ReferenceSettings()
        self.vertices, self.triangles = _as_mesh_arrays(vertices, triangles)
        self.boundary = np.asarray(boundary, dtype=np.int64)
        self.camera = camera
        self.problem = GroupLassoProblem(
            self.vertices, self.triangles, self.boundary, E, nu, thickness, k_f, k_u
        )
        self.k_const = float(k_const)
        self.k_linear = float(k_linear)
        self.reference_pressure_pa = float(reference_pressure_pa)
        self._ref_grey = cv2.cvtColor(np.ascontiguousarray(reference_rgb), cv2.COLOR_RGB2GRAY)
        self._node_uv, _ = camera.project(self.vertices)
        if self.settings.subtract_reference_lift:
            self._x_ref = self._lift(np.asarray(reference_depth), self._node_uv)
        else:
            self._x_ref = self.vertices.copy()

    @classmethod
    def from_mesh(
        cls, mesh: Any, camera: Camera, reference: Any, **kwargs: Any
    ) -> ReferencePipeline:
        """Build from a ``Mesh`` and a reference with ``.rgb``, ``.depth``, ``.pressure_pa``."""
        return cls(
            mesh.vertices,
            mesh.triangles,
            mesh.boundary,
            camera,
            reference.rgb,
            reference.depth,
            reference.pressure_pa,
            **kwargs,
        )

    def _flow(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        import cv2

        s = self.settings
        grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        flow = cv2.calcOpticalFlowFarneback(  # type: ignore[call-overload]
            self._ref_grey,
            grey,
            None,
            s.pyr_scale,
            s.levels,
            s.winsize,
            s.iterations,
            s.poly_n,
            s.poly_sigma,
            cv2.OPTFLOW_FARNEBACK_GAUSSIAN,
        )
        return np.asarray(flow, dtype=np.float32)

    def _filtered_cloud(self, depth: NDArray) -> NDArray[np.float64]:
        from scipy.spatial import cKDTree

        s = self.settings
        st = max(int(s.cloud_stride), 1)
        H, W = depth.shape
        v, u = np.mgrid[0:H:st, 0:W:st]
        d = np.asarray(depth, dtype=np.float64)[v, u].ravel()
        ok = np.isfinite(d) & (d > 0)
        uv = np.column_stack([u.ravel()[ok], v.ravel()[ok]]).astype(np.float64)
        pts = self.camera.backproject(uv, d[ok])
        # Heights are measured from the mesh's lowest point (the rim plane in the mesh frame).
        z0 = float(self.vertices[:, 2].min())
        keep = (pts[:, 2] > z0 - s.z_tol) & (pts[:, 2] < z0 + s.max_height + s.z_tol)
        pts = pts[keep]
        k = int(s.outlier_neighbors)
        if k > 0 and len(pts) > k + 1:
            dd, _ = cKDTree(pts).query(pts, k=k + 1)
            # Sample spacing grows with camera distance; normalising by it keeps the far
            # (sparser) part of the dome from being taken for outliers.
            zc = np.maximum(self.camera.to_camera(pts)[:, 2], 1e-6)
            md = dd[:, 1:].mean(axis=1) / zc
            pts = pts[md <= md.mean() + s.outlier_std_ratio * md.std()]
        return pts  # type: ignore[no-any-return]

    def _lift(self, depth: NDArray, query_uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """S(query_uv): griddata over the projected filtered cloud plus the fixed rim nodes."""
        from scipy.interpolate import griddata

        pts = self._filtered_cloud(depth)
        # The clamped rim anchors the interpolation hull, as the public code does with its ellipse.
        rim = self.vertices[self.boundary]
        pts = np.vstack([pts, rim])
        uv, _ = self.camera.project(pts)
        out = np.asarray(griddata(uv, pts, query_uv, method="linear"))
        bad = ~np.all(np.isfinite(out), axis=1)
        if np.any(bad):
            out[bad] = np.asarray(griddata(uv, pts, query_uv[bad], method="nearest"))
        return out

    def process(self, rgb: NDArray[np.uint8], depth: NDArray, pressure_pa: float) -> dict[str, Any]:
        """Run one frame; returns node_forces (N x 3, N), net_force (3,), contact (N,),
        normal_pressure (N,), displacements (N x 3 corrected, m), raw_displacements,
        objective, status and timings_ms {flow, lift, solve, post}."""
        t0 = time.perf_counter()
        flow = self._flow(rgb)
        t1 = time.perf_counter()
        from scipy.ndimage import map_coordinates

        uvn = self._node_uv
        fu = map_coordinates(flow[..., 0], [uvn[:, 1], uvn[:, 0]], order=1, mode="nearest")
        fv = map_coordinates(flow[..., 1], [uvn[:, 1], uvn[:, 0]], order=1, mode="nearest")
        x_cur = self._lift(np.asarray(depth), uvn + np.column_stack([fu, fv]))
        U = x_cur - self._x_ref
        U[self.boundary] = 0.0
        dp = float(pressure_pa) - self.reference_pressure_pa
        t2 = time.perf_counter()
        dU, obj = self.problem.solve(U, dp, tight=self.settings.tight)
        t3 = time.perf_counter()
        Uc = U + dU
        pb = self.problem
        F = pb.forces(Uc, dp)
        p = normal_pressure(F, pb.areas, pb.normals)
        contact = contact_mask(p, pb.areas, self.k_const, self.k_linear)
        f_net = net_force(F, self.boundary)
        t4 = time.perf_counter()
        return {
            "node_forces": F,
            "net_force": f_net,
            "contact": contact,
            "normal_pressure": p,
            "displacements": Uc,
            "raw_displacements": U,
            "dp": dp,
            "objective": obj,
            "status": pb.last_status,
            "timings_ms": {
                "flow": 1e3 * (t1 - t0),
                "lift": 1e3 * (t2 - t1),
                "solve": 1e3 * (t3 - t2),
                "post": 1e3 * (t4 - t3),
            },
        }


def _timing_main(argv: list[str] | None = None) -> int:
    """``python3 -m bubble_rt.reference``: time the CVXPY solve and the full reference pipeline."""
    import argparse

    import cv2

    from bubble_rt.camera import Camera
    from bubble_rt.mesh import Mesh

    ap = argparse.ArgumentParser(description=_timing_main.__doc__)
    ap.add_argument("--mesh", default="medium", help="coarse | medium | fine")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--stride", type=int, default=ReferenceSettings.cloud_stride)
    ap.add_argument("--solve-only", action="store_true", help="time only the CVXPY solve")
    args = ap.parse_args(argv)
    mesh = Mesh.preset(args.mesh)
    V, T = mesh.vertices, mesh.triangles
    normals = vertex_normals(V, T)
    rng = np.random.default_rng(0)

    def bump(k: int) -> NDArray[np.float64]:
        amp = 4e-3 * np.sin(np.pi * (k + 0.5) / args.frames)
        cx = -0.02 + 0.04 * k / max(args.frames - 1, 1)
        c = np.exp(-((V[:, 0] - cx) ** 2 + V[:, 1] ** 2) / (2 * 0.008**2))
        c[mesh.boundary] = 0
        return -amp * c[:, None] * normals  # type: ignore[no-any-return]

    if args.solve_only:
        pb = GroupLassoProblem(V, T, mesh.boundary)
        times = []
        for k in range(args.frames):
            U = bump(k) + 1e-4 * rng.standard_normal(V.shape)
            U[mesh.boundary] = 0
            pb.solve(U, 30.0)
            times.append(pb.last_solve_ms)
        print(
            f"reference CVXPY+Clarabel solve, {args.mesh} ({mesh.n_nodes} nodes), "
            f"{args.frames} frames: p50 {np.median(times):.1f} ms, max {np.max(times):.1f} ms"
        )
        return 0

    cam = Camera.d405()
    img = cv2.GaussianBlur(rng.random((cam.height, cam.width)).astype(np.float32), (0, 0), 2.0)
    img = (255 * (img - img.min()) / (img.max() - img.min())).astype(np.uint8)
    rgb_ref = np.repeat(img[:, :, None], 3, axis=2)
    pipe = ReferencePipeline(
        V,
        T,
        mesh.boundary,
        cam,
        rgb_ref,
        render_depth(V, T, cam),
        1e5,
        settings=ReferenceSettings(cloud_stride=args.stride),
    )
    from scipy.interpolate import griddata

    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    uv0, _ = cam.project(V)
    stages: dict[str, list[float]] = {}
    total = []
    for k in range(args.frames):
        U = bump(k)
        uv1, _ = cam.project(V + U)
        back = griddata(uv1, uv0 - uv1, (xx, yy), method="linear", fill_value=0.0)
        back = np.asarray(back, dtype=np.float32)
        rgb = np.asarray(
            cv2.remap(rgb_ref, xx + back[..., 0], yy + back[..., 1], cv2.INTER_LINEAR),
            dtype=np.uint8,
        )
        depth = render_depth(V + U, T, cam)
        t = time.perf_counter()
        out = pipe.process(rgb, depth, 1e5 + 30.0)
        total.append(1e3 * (time.perf_counter() - t))
        for key, val in out["timings_ms"].items():
            stages.setdefault(key, []).append(val)
    st = ", ".join(f"{k} {np.median(v):.0f}" for k, v in stages.items())
    print(
        f"reference pipeline, {args.mesh} ({mesh.n_nodes} nodes), 640x480, cloud stride "
        f"{args.stride}, {args.frames} frames: per frame p50 {np.median(total):.0f} ms "
        f"({1e3 / np.median(total):.2f} Hz); stages p50 ms: {st}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(_timing_main())
