"""Warm-started ADMM solver for the regularised force estimate (docs/method.md, "How the
solver works").

Solves, per frame,

    minimise   sum_i w_i ||F_ext(U + dU, dp)_i||  +  (k_u / N) sum_i ||dU_i||^2
    subject to (U + dU)_i = 0 on the rim

with w_i = k_f |rim| / N on the rim and k_f elsewhere. The rim is exact (its dofs are
eliminated). The C++ core runs an OSQP-shaped ADMM: split z = F_ext, x-update a sparse LDLT
solve factored once per rho (factorizations are cached), z-update a block soft-threshold,
over-relaxation, Anderson acceleration, warm start from the previous frame's corrected
displacement and multipliers. rho follows the data (weights over the previous solution's force scale),
so the iterations are unchanged by a change of units.
Termination is certified: every dual iterate is feasible, so the duality gap bounds how far
the returned objective is above the optimum.
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt import _core, _validate
from bubble_rt.estimation.membrane import MembraneModel

Status = Literal["solved", "max_iter_reached", "time_limit_reached", "non_finite_input"]


#: The C++ defaults (bubble::SolverSettings in cpp/group_lasso.h), read through the binding.
_CORE_DEFAULTS = _core._SolverSettings()


@dataclass(frozen=True)
class SolverSettings:
    """ADMM settings (mirrors bubble::SolverSettings in cpp/group_lasso.h; the defaults are
    the C++ ones, read through the binding).

    Attributes:
        rho: step-size multiplier. The actual ADMM rho of the (non-dimensionalised) problem
            is ``rho * mean(weights) / force scale``, the force scale being the rms nodal force
            of the previous frame's solution (tiny on untouched frames, large in contact); it
            is re-set only when it moves by more than ``adaptive_rho_tolerance``.
        sigma: proximal term of the x-update (keeps it well posed; tiny).
        alpha: over-relaxation, in (0, 2).
        adaptive_rho: re-apply the rho rule inside a solve, from the current iterate's
            forces, every ``adaptive_rho_interval`` iterations (a contact made or released
            between two frames).
        adaptive_rho_tolerance: factor by which rho must move before refactoring.
        adaptive_rho_interval: iterations between in-solve rho updates.
        eps_abs: absolute duality-gap tolerance (the objective is dimensionless).
        eps_rel: relative duality-gap tolerance: "solved" guarantees
            objective - optimum <= eps_abs + eps_rel * objective.
        max_iter: iteration cap ("max_iter_reached" status, the last iterate is returned).
        check_interval: most iterations between termination checks; a check comes earlier
            when the duality gap's rate since the last one predicts certification sooner.
        time_limit: seconds per warm-started solve, 0 = none ("time_limit_reached" status).
            A cold solve (the first, or after ``cold_start``) runs to certification or
            ``max_iter``: stopped early, its multipliers sit on their bounds at most nodes and
            the support read from them is noise.
        scaling_iter: Ruiz equilibration passes (0 = a scalar non-dimensionalisation only).
        warm_start: start each solve from the previous frame's solution.
        anderson_memory: Anderson acceleration memory on the ADMM fixed-point map (0 = off);
            restarts automatically when the fixed-point residual jumps.
    """

    rho: float = float(_CORE_DEFAULTS.rho)
    sigma: float = float(_CORE_DEFAULTS.sigma)
    alpha: float = float(_CORE_DEFAULTS.alpha)
    adaptive_rho: bool = bool(_CORE_DEFAULTS.adaptive_rho)
    adaptive_rho_tolerance: float = float(_CORE_DEFAULTS.adaptive_rho_tolerance)
    adaptive_rho_interval: int = int(_CORE_DEFAULTS.adaptive_rho_interval)
    eps_abs: float = float(_CORE_DEFAULTS.eps_abs)
    eps_rel: float = float(_CORE_DEFAULTS.eps_rel)
    max_iter: int = int(_CORE_DEFAULTS.max_iter)
    check_interval: int = int(_CORE_DEFAULTS.check_interval)
    time_limit: float = float(_CORE_DEFAULTS.time_limit)
    scaling_iter: int = int(_CORE_DEFAULTS.scaling_iter)
    warm_start: bool = bool(_CORE_DEFAULTS.warm_start)
    anderson_memory: int = int(_CORE_DEFAULTS.anderson_memory)

    def __post_init__(self) -> None:
        try:
            self._to_core().validate()
        except (ValueError, TypeError) as exc:
            raise ValueError(f"invalid SolverSettings: {exc}") from exc

    @classmethod
    def tight(cls, **changes: object) -> SolverSettings:
        """Certified relative objective gap below 1e-5 (eps_rel 8e-6, longer Anderson memory)."""
        base = cls(eps_rel=8e-6, eps_abs=1e-8, max_iter=20000, anderson_memory=10)
        return replace(base, **changes)  # type: ignore[arg-type]

    def _to_core(self):  # noqa: ANN202 - private binding type
        s = _core._SolverSettings()
        for k, v in asdict(self).items():
            setattr(s, k, v)
        return s


@dataclass(frozen=True)
class SolverInfo:
    """Outcome of one solve.

    Attributes:
        status: "solved", "max_iter_reached", "time_limit_reached" or "non_finite_input".
        iterations: ADMM iterations run.
        primal_residual: ||A x - z||_inf (N).
        dual_residual: ||P x + A^T y||_inf (1/m, dimensionless objective per metre).
        objective: objective at the returned dU (dimensionless).
        duality_gap: objective minus the best dual bound (>= 0).
        rho: ADMM step in use (non-dimensional problem).
        setup_time_ms: factorization time spent inside this solve (0 when rho's factor was
            cached; the first solve factors at the data-driven rho).
        solve_time_ms: time of this solve in C++.
        factorizations: factorizations computed during this solve (0 when every rho it used
            was cached; the cache keeps every rho a run visits, within 64 MB).
    """

    status: Status
    iterations: int
    primal_residual: float
    dual_residual: float
    objective: float
    duality_gap: float = 0.0
    rho: float = 0.0
    setup_time_ms: float = 0.0
    solve_time_ms: float = 0.0
    factorizations: int = 0

    @classmethod
    def _from_core(cls, i) -> SolverInfo:  # noqa: ANN001
        return cls(
            status=i.status,
            iterations=int(i.iterations),
            primal_residual=float(i.primal_residual),
            dual_residual=float(i.dual_residual),
            objective=float(i.objective),
            duality_gap=float(i.duality_gap),
            rho=float(i.rho),
            setup_time_ms=float(i.setup_time_ms),
            solve_time_ms=float(i.solve_time_ms),
            factorizations=int(i.factorizations),
        )


@dataclass(frozen=True)
class SolverResult:
    """dU (N x 3, m; rim rows = -U_rim), dual (N x 3, multipliers of F_ext, ||y_i|| <= w_i)."""

    dU: NDArray[np.float64]
    dual: NDArray[np.float64]
    info: SolverInfo


class GroupLassoSolver:
    """Facade over the C++ ADMM solver; one instance per mesh, reused frame after frame.

    ``update(U, dp)`` then ``solve()``; the next solve warm-starts from this one unless
    ``settings.warm_start`` is False or ``cold_start()`` was called. Calls are serialised by
    a lock; the GIL is released while C++ works, so other Python threads keep running.
    """

    def __init__(
        self,
        model: MembraneModel,
        k_f: float = 0.3322,
        k_u: float = 537592.0,
        settings: SolverSettings | None = None,
    ) -> None:
        self.model = model
        self._settings = settings or SolverSettings()
        k_f = _validate.positive("k_f", k_f)
        k_u = _validate.positive("k_u", k_u)
        self._k = (k_f, k_u)
        self._lock = threading.Lock()
        self._n = model.n_nodes
        self._impl = _core._GroupLassoSolver(
            model._core,
            np.ascontiguousarray(model.mesh.boundary, dtype=np.int32),
            k_f,
            k_u,
            self._settings._to_core(),
        )

    @property
    def settings(self) -> SolverSettings:
        return self._settings

    @property
    def weights(self) -> tuple[float, float]:
        """(k_f, k_u) in use (1/N, 1/m^2)."""
        return self._k

    def set_settings(self, settings: SolverSettings) -> None:
        """New settings; refactors only when rho, sigma or scaling changed."""
        with self._lock:
            self._impl.set_settings(settings._to_core())
            self._settings = settings

    def set_weights(self, k_f: float, k_u: float) -> None:
        """New k_f (1/N) and k_u (1/m^2); rescales and refactors (milliseconds)."""
        k_f = _validate.positive("k_f", k_f)
        k_u = _validate.positive("k_u", k_u)
        with self._lock:
            self._impl.set_weights(k_f, k_u)
            self._k = (k_f, k_u)

    def update(self, U: ArrayLike, dp: float) -> None:
        """Frame data: displacements U (N x 3, m) and pressure change dp (Pa)."""
        U = _validate.nodes_x3("U", U, self._n)
        dp = _validate.finite_scalar("dp", dp)
        with self._lock:
            self._impl.update(U, dp)

    def warm_start(self, primal: ArrayLike, dual: ArrayLike) -> None:
        """Start the next solve from corrected displacements ``primal`` = U + dU (N x 3, m)
        and multipliers ``dual`` (N x 3) from an earlier SolverResult."""
        V = _validate.nodes_x3("primal", primal, self._n)
        Y = _validate.nodes_x3("dual", dual, self._n)
        with self._lock:
            self._impl.warm_start(V, Y)

    def cold_start(self) -> None:
        """Make the next solve start as the first one did: dU = 0, zero multipliers, and rho
        chosen from that frame's data (the previous frame's force scale forgotten)."""
        with self._lock:
            self._impl.cold_start()

    def solve(self) -> SolverResult:
        """Solve for the current frame. Non-convergence is reported in info.status."""
        with self._lock:
            dU, dual, info = self._impl.solve()
        return SolverResult(np.asarray(dU), np.asarray(dual), SolverInfo._from_core(info))

    def solve_frame(self, U: ArrayLike, dp: float) -> SolverResult:
        """``update(U, dp)`` then ``solve()``."""
        self.update(U, dp)
        return self.solve()
