"""Paper-faithful membrane model (the paper's linear model, without inflation) in plain
NumPy/SciPy: CST stiffness, lumped areas, normals, forces, contact rule.

Lumped areas and normals are also computed by the product (``bubble_rt.mesh`` and the C++
membrane model). This copy is kept on purpose: the reference is the yardstick the C++ path is
tested against, so it shares no code with it (import-linter forbids ``bubble_rt.estimation``
here)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray


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
    """Assembled CST plane-stress stiffness K (3N x 3N, N/m, csr), the paper's linear model.

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
    return nsum / norm[:, None]


def external_forces(
    K: sp.spmatrix, U: ArrayLike, dp: float, areas: ArrayLike, normals: ArrayLike
) -> NDArray[np.float64]:
    """Contact forces F_ext = K U - dp a n (N x 3, newtons) for displacements U (N x 3, m)."""
    U = np.asarray(U, dtype=np.float64)
    a = np.asarray(areas, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    return (K @ U.reshape(-1)).reshape(-1, 3) - float(dp) * a[:, None] * n


def normal_pressure(F: ArrayLike, areas: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Inward normal pressure p_i = -n_i . F_i / a_i (N,), Pa."""
    F = np.asarray(F, dtype=np.float64)
    return -np.einsum("ij,ij->i", F, np.asarray(normals)) / np.asarray(areas)


def contact_mask(
    normal_pressure: ArrayLike,
    areas: ArrayLike,
    k_const: float = 2000.0,
    k_linear: float = 2.0,
) -> NDArray[np.bool_]:
    """Contact nodes: ``p_v > max(k_const, k_linear * (a . p) / sum(a))`` (docs/method.md,
    "Contact rule")."""
    p = np.asarray(normal_pressure, dtype=np.float64)
    a = np.asarray(areas, dtype=np.float64)
    thresh = max(k_const, k_linear * float(a @ p) / float(a.sum()))
    return p > thresh


def net_force(F: ArrayLike, boundary: ArrayLike) -> NDArray[np.float64]:
    """Net contact force (3,), N: F summed over the non-rim nodes."""
    F = np.asarray(F, dtype=np.float64)
    keep = np.ones(len(F), dtype=bool)
    keep[np.asarray(boundary, dtype=np.int64)] = False
    return F[keep].sum(axis=0)


def lasso_weights(n_nodes: int, boundary: ArrayLike, k_f: float) -> NDArray[np.float64]:
    """Group-lasso force weights w_i (N,): k_f |dM| / N on the rim, k_f elsewhere."""
    b = np.asarray(boundary, dtype=np.int64)
    w = np.full(n_nodes, float(k_f))
    w[b] = k_f * len(b) / n_nodes
    return w
