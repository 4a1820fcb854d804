"""Types shared by the estimators (the FEM estimator and the frictionless baseline), so that
neither imports the other."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from bubble_rt.estimation.solver import SolverInfo


@dataclass
class Estimate:
    """One frame's estimate (all arrays over the N mesh nodes, mesh frame).

    Attributes:
        node_forces: N x 3 force the object applies on each node (N).
        contact_pressure: N x 3 node_forces / lumped area (Pa).
        normal_pressure: (N,) -n . contact_pressure (Pa, inward positive).
        contact: (N,) bool contact mask.
        net_force: (3,) sum of node_forces over non-rim nodes (N).
        displacements: N x 3 corrected displacements U + dU (m), zero on the rim (refitted).
        info: SolverInfo of the solve.
        timings_ms: stage -> milliseconds ("solve", "refit", "post"; "flow", "lift" from
            process()).
        valid_node_fraction: fraction of nodes the deformation stage measured (1.0 for U given).
        support: (N,) bool, the group lasso's support (interior nodes that carry force; empty
            for estimators without one).
        degraded_reasons: why the input or the result is implausible
            (:mod:`bubble_rt.estimation.plausibility`); empty for a healthy frame.
        pressure_delta_pa: the frame's pressure minus the reference's (Pa), as the estimate
            used it (``Reference.pressure_change``; set by the Pipeline).
        rule_pressure: (N,) Pa, inward positive: the linear refit's normal pressure, which the
            contact rule thresholds and which weights a patch's ``pressure_centroid`` (empty:
            ``normal_pressure`` is that pressure). The nonlinear refit's forces gather at a
            dent's edge, so their pressure places the load's centre worse (docs/evaluation.md).
        patch_label: (N,) int, the contact rule's load region of each contact node (-1
            elsewhere): contact nodes with one label are one patch, connected or not (empty:
            patches are the contact's connected components).
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
    support: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    degraded_reasons: list[str] = field(default_factory=list)
    pressure_delta_pa: float = 0.0
    rule_pressure: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    patch_label: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
