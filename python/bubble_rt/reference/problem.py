"""The paper's group-lasso problem built once in CVXPY and solved with Clarabel."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from bubble_rt.reference.model import (
    _as_mesh_arrays,
    external_forces,
    lasso_weights,
    lumped_areas,
    stiffness_matrix,
    vertex_normals,
)

if TYPE_CHECKING:
    pass


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
        # The minimiser depends only on k_u / k_f; that ratio is a Parameter (DPP), so
        # calibration sweeps need no re-canonicalisation. Objective values come from NumPy.
        self._ratio = cp.Parameter(nonneg=True, name="k_u_over_k_f")
        self._ratio.value = self._ratio_value()
        base_w = lasso_weights(n, self.boundary, 1.0)
        objective = base_w @ norms + self._ratio * cp.sum_squares(self._x)
        self._problem = cp.Problem(cp.Minimize(objective))
        self.last_status: str = ""
        self.last_solve_ms: float = float("nan")

    def reconfigure(self, k_f: float | None = None, k_u: float | None = None) -> None:
        """Change the weights k_f (1/N) and k_u (1/m^2) without rebuilding the problem."""
        if k_f is not None:
            if not k_f > 0:
                raise ValueError(f"k_f must be positive, got {k_f}")
            self.k_f = float(k_f)
            self.weights = lasso_weights(self.n, self.boundary, self.k_f)
        if k_u is not None:
            if not k_u > 0:
                raise ValueError(f"k_u must be positive, got {k_u}")
            self.k_u = float(k_u)
        self._ratio.value = self._ratio_value()

    def _ratio_value(self) -> float:
        return self.k_u / (self.k_f * self.n) * self._VAR_SCALE**2

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
