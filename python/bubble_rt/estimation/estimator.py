"""Force and contact estimation from nodal displacements (method.md sections 2-3).

``ForceEstimator.estimate(U, dp)`` corrects the measured displacements with the group-lasso
solver and derives the nodal forces, contact pressure, contact mask and net force from the
corrected field. ``process(frame)`` runs an attached deformation tracker first.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt import _validate
from bubble_rt.estimation.membrane import Material, MembraneModel
from bubble_rt.estimation.solver import GroupLassoSolver, SolverInfo, SolverSettings
from bubble_rt.mesh import Mesh


@dataclass(frozen=True)
class EstimatorConfig:
    """Estimator parameters (paper defaults).

    Attributes:
        material: membrane Material (E Pa, nu, thickness m).
        k_f: force sparsity weight (1/N).
        k_u: displacement-correction weight (1/m^2).
        k_const: absolute contact threshold on normal pressure (Pa).
        k_linear: contact threshold relative to the area-weighted mean normal pressure (-).
        solver: ADMM SolverSettings.
    """

    material: Material = field(default_factory=Material)
    k_f: float = 0.3322
    k_u: float = 537592.0
    k_const: float = 2000.0
    k_linear: float = 2.0
    solver: SolverSettings = field(default_factory=SolverSettings)

    def __post_init__(self) -> None:
        if not isinstance(self.material, Material):
            raise ValueError(f"material must be a Material, got {type(self.material).__name__}")
        if not isinstance(self.solver, SolverSettings):
            raise ValueError(f"solver must be a SolverSettings, got {type(self.solver).__name__}")
        _validate.positive("k_f", self.k_f)
        _validate.positive("k_u", self.k_u)
        _validate.finite_scalar("k_const", self.k_const)
        _validate.finite_scalar("k_linear", self.k_linear)


@dataclass
class Estimate:
    """One frame's estimate (all arrays over the N mesh nodes, mesh frame).

    Attributes:
        node_forces: N x 3 force the object applies on each node (N).
        contact_pressure: N x 3 node_forces / lumped area (Pa).
        normal_pressure: (N,) -n . contact_pressure (Pa, inward positive).
        contact: (N,) bool contact mask.
        net_force: (3,) sum of node_forces over non-rim nodes (N).
        displacements: N x 3 corrected displacements U + dU (m), zero on the rim.
        info: SolverInfo of the solve.
        timings_ms: stage -> milliseconds ("solve", "post"; "flow", "lift" from process()).
        valid_node_fraction: fraction of nodes the deformation stage measured (1.0 for U given).
    """

    node_forces: NDArray[np.float64]
    contact_pressure: NDArray[np.float64]
    normal_pressure: NDArray[np.float64]
    contact: NDArray[np.bool_]
    net_force: NDArray[np.float64]
    displacements: NDArray[np.float64]
    info: SolverInfo
    timings_ms: dict[str, float] = field(default_factory=dict)
    valid_node_fraction: float = 1.0


class _Tracker(Protocol):
    def track(self, frame: Any) -> Any: ...


class ForceEstimator:
    """The paper's FEM + group-lasso estimator with the ADMM core.

    Attributes:
        mesh: reference Mesh.
        config: EstimatorConfig in use.
        model: MembraneModel (rebuilt only when the material changes).
        solver: GroupLassoSolver (warm-started across calls).
    """

    def __init__(self, mesh: Mesh, config: EstimatorConfig | None = None) -> None:
        self.mesh = mesh
        self.config = config or EstimatorConfig()
        self.model = MembraneModel(mesh, self.config.material)
        self.solver = GroupLassoSolver(
            self.model, self.config.k_f, self.config.k_u, self.config.solver
        )
        self._tracker: _Tracker | None = None

    def estimate(self, U: ArrayLike, dp: float) -> Estimate:
        """Estimate from displacements U (N x 3, m, mesh frame) and pressure change dp (Pa).

        Raises ValueError (naming the argument) on a wrong shape or NaN/inf; the solver's
        warm-start state is then left as it was.
        """
        t0 = time.perf_counter()
        res = self.solver.solve_frame(U, dp)
        t1 = time.perf_counter()
        est = self._post(np.asarray(U, dtype=np.float64) + res.dU, float(dp), res.info)
        est.timings_ms = {"solve": 1e3 * (t1 - t0), "post": 1e3 * (time.perf_counter() - t1)}
        return est

    def _post(self, V: NDArray[np.float64], dp: float, info: SolverInfo) -> Estimate:
        m = self.model
        V[self.mesh.boundary] = 0.0  # exact already; removes the -0.0 / round-off noise
        if info.status == "non_finite_input":
            F = np.zeros_like(V)
        else:
            F = m.external_forces(V, dp)
        P = F / m.areas[:, None]
        p = m.normal_pressure(F)
        contact = m.contact_mask(p, self.config.k_const, self.config.k_linear)
        return Estimate(
            node_forces=F,
            contact_pressure=P,
            normal_pressure=p,
            contact=contact,
            net_force=m.net_force(F),
            displacements=V,
            info=info,
        )

    def reconfigure(self, **changes: Any) -> None:
        """Change config fields in place (EstimatorConfig field names).

        k_f / k_u refactor the solver (milliseconds), k_const / k_linear are free, solver
        settings are applied without rebuilding, material rebuilds K and the solver.
        """
        new = dataclasses.replace(self.config, **changes)  # validates
        if new.material != self.config.material:
            model = MembraneModel(self.mesh, new.material)
            solver = GroupLassoSolver(model, new.k_f, new.k_u, new.solver)
            self.model, self.solver = model, solver
        else:
            if (new.k_f, new.k_u) != (self.config.k_f, self.config.k_u):
                self.solver.set_weights(new.k_f, new.k_u)
            if new.solver != self.config.solver:
                self.solver.set_settings(new.solver)
        self.config = new

    def attach(self, tracker: _Tracker) -> None:
        """Use ``tracker.track(frame) -> Deformation`` (U, dp, valid_fraction, timings_ms)."""
        if not hasattr(tracker, "track"):
            raise ValueError("tracker must have a track(frame) method")
        self._tracker = tracker

    def process(self, frame: Any) -> Estimate:
        """Track the frame with the attached tracker, then estimate."""
        if self._tracker is None:
            raise RuntimeError("no deformation tracker attached: call attach(tracker) first")
        d = self._tracker.track(frame)
        est = self.estimate(d.U, d.dp)
        timings = dict(getattr(d, "timings_ms", {}) or {})
        timings.update(est.timings_ms)
        est.timings_ms = timings
        est.valid_node_fraction = float(getattr(d, "valid_fraction", 1.0))
        return est


def make_estimator(
    kind: str,
    mesh: Mesh,
    config: EstimatorConfig | None = None,
    camera: Any = None,
    reference: Any = None,
) -> Any:
    """An estimator by name: "fem" (ForceEstimator) or "frictionless" (Kuppuswamy baseline,
    needs ``camera`` and ``reference``)."""
    if kind == "fem":
        return ForceEstimator(mesh, config)
    if kind == "frictionless":
        from bubble_rt.estimation.baseline import FrictionlessEstimator  # type: ignore[import-not-found]

        return FrictionlessEstimator(mesh, camera, reference, config)
    raise ValueError(f"unknown estimator kind {kind!r}; choose 'fem' or 'frictionless'")
