"""Force and contact estimation from nodal displacements (method.md sections 2-3).

``ForceEstimator.estimate(U, dp)`` corrects the measured displacements with the group-lasso
solver and derives the nodal forces, contact pressure, contact mask and net force from the
corrected field. ``process(frame)`` runs an attached deformation tracker first.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt import _validate
from bubble_rt.estimation.membrane import Material, MembraneModel
from bubble_rt.estimation.solver import GroupLassoSolver, SolverInfo, SolverSettings
from bubble_rt.estimation.types import Estimate
from bubble_rt.mesh import Mesh

__all__ = [
    "CONFIG_KEYS",
    "Estimate",
    "EstimatorConfig",
    "ForceEstimator",
    "config_changes",
]


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


#: The TOML ``[estimator]`` keys (daemon config, ``set_params``, ``bubble-rt calibrate``'s output)
#: and the EstimatorConfig field each one sets: (field, material field or None).
CONFIG_KEYS: dict[str, tuple[str, str | None]] = {
    "k_f": ("k_f", None),
    "k_u": ("k_u", None),
    "k_const": ("k_const", None),
    "k_linear": ("k_linear", None),
    "youngs_modulus": ("material", "E"),
    "poisson": ("material", "nu"),
    "thickness": ("material", "thickness"),
}


def config_changes(config: EstimatorConfig, values: Mapping[str, float]) -> dict[str, Any]:
    """``dataclasses.replace`` changes of ``config`` for ``[estimator]`` key values (CONFIG_KEYS);
    ValueError names a key that is not one."""
    changes: dict[str, Any] = {}
    material: dict[str, float] = {}
    for key, value in values.items():
        if key not in CONFIG_KEYS:
            raise ValueError(
                f"{key!r} is not an estimator parameter; use one of {list(CONFIG_KEYS)}"
            )
        name, sub = CONFIG_KEYS[key]
        if sub is None:
            changes[name] = float(value)
        else:
            material[sub] = float(value)
    if material:
        changes["material"] = replace(config.material, **material)
    return changes


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
