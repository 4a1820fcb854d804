"""Force and contact estimation from nodal displacements (docs/method.md).

``ForceEstimator.estimate(U, dp)`` runs three steps on the measured displacements:

1. **group lasso** (the paper's regularised estimate, ADMM in C++): which nodes carry force
   (those whose multiplier is within ``support_tol`` of its bound),
   on the membrane linearised about its inflated reference (``MembraneModel(...,
   inflation_pa)``: material + geometric stiffness of the inflation tension + load stiffness
   of the rest pressure);
2. **refit** (relaxed group lasso, C++ ``SupportRefit``): the forces re-estimated on the
   lasso's support without the L1 term, i.e. the smallest correction of U whose forces vanish
   off the support. The lasso finds the support; its shrinkage (a roughly fixed amount off
   every force group, which erased light touches) is undone;
3. **contact**: the support nodes whose inward pressure passes the paper's threshold
   ``max(k_const, k_linear * area-weighted mean p)`` and whose pressure averaged over a disc of
   ``peak_radius_m`` reaches ``k_peak`` times the peak of their load (:func:`load_regions`:
   the support's highest peak, unless a saddle separates a second load that carries at least
   ``k_load`` of the first one's force). Pressures, multipliers and the disc are per area or
   physical lengths, so the patch does not shrink as the mesh refines
   (docs/mesh-convergence.md). Each load region is one contact patch (``patch_label``),
   filled to the convex hull of its contact nodes (:func:`fill_load_hulls`).

Nodal forces, contact pressure, contact mask and net force come from the refitted field.
``process(frame)`` runs an attached deformation tracker first.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from bubble_rt import _validate
from bubble_rt.estimation.membrane import Material, MembraneModel
from bubble_rt.estimation.params import ESTIMATOR_PARAMS
from bubble_rt.estimation.solver import GroupLassoSolver, SolverInfo, SolverSettings
from bubble_rt.estimation.types import Estimate
from bubble_rt.mesh import Mesh
from bubble_rt.sensor import SIM

__all__ = [
    "CONFIG_KEYS",
    "Estimate",
    "EstimatorConfig",
    "ForceEstimator",
    "config_changes",
]

#: Membrane material of the default estimator (the declared defaults: the simulator's bubble).
DEFAULT_MATERIAL = Material(
    **{p.material: p.default for p in ESTIMATOR_PARAMS.values() if p.material is not None}
)
#: Pressures above this are taken as absolute when deriving the rest gauge pressure (Pa).
ABSOLUTE_PRESSURE_MIN = 30e3


@dataclass(frozen=True)
class EstimatorConfig:
    """Estimator parameters (k_u, k_const, k_linear: the paper's; see DEFAULT_MATERIAL for E).

    Attributes:
        material: membrane Material (E Pa, nu, thickness m).
        k_f: force sparsity weight of the group lasso (1/N). It only picks the support now
            (the refit removes its shrinkage): 0.05, a sixth of the paper's 0.3322, so the
            first frames of a 0.1-0.3 N touch keep a support. Chosen with E on the calibration
            seeds (`bubble-rt eval --seed 1000`, E 0.5-0.6 MPa): light-touch detection 0.96 at
            0.05, 0.90-0.94 at 0.07, 0.85 at 0.1 (E 0.66 MPa). 0.03 read better there (1.00,
            0.16 N against 0.18 N) but keeps a 0.55 N phantom support on an untouched real
            Punyo frame with the sim profile (tests/test_phantom.py); 0.02 marks 1.5-2 % of
            the simulated untouched frames in contact.
        k_u: displacement-correction weight (1/m^2), per node k_u / N as in the paper's text.
        k_const: absolute contact threshold on normal pressure (Pa).
        k_linear: contact threshold relative to the area-weighted mean normal pressure (-).
        k_peak: contact threshold relative to the peak normal pressure of the node's load
            region over the support (-).
        k_load: a support region that the disc pressure separates from a higher one (through
            nodes below ``k_peak`` times its own peak) is a load of its own when its core (its
            nodes at ``k_peak`` of its peak) carries at least this fraction of the strongest
            load's core force; otherwise it is measured against the higher peak (-). Chosen
            on the calibration seeds (docs/evaluation.md, "Loads of their own").
        k_join: two regions that meet where the disc pressure is at least this multiple of
            the gas's gauge pressure (rest plus change) are one load, whatever ``k_load``
            says (-). A face pressed flat carries the gauge pressure between its loaded edges;
            free membrane between two pins carries none. Chosen on the calibration seeds
            (docs/evaluation.md, "One face, one load").
        support_tol: support rule (-): a node carries force when its multiplier is within this
            fraction of its bound, ``||y_i|| >= (1 - support_tol) k_f`` (``support``).
        peak_radius_m: the ``k_peak`` rule compares normal pressures averaged over the nodes
            within this distance (m) of each node, the node itself included (``disc_pressure``).
        inflation_pa: rest gauge pressure (Pa) the membrane is linearised about, used when the
            estimator is not given a reference (a reference's pressure replaces it).
        ambient_pa: ambient pressure (Pa), subtracted from an absolute reference pressure: it
            sets the rest gauge pressure, hence the rest tension that governs the force a dent
            means (bubble_rt.sensor).
        nonlinear_iterations: the refit's forces are those of the membrane with its geometric
            nonlinearity (``GreenMembrane``: Green strain, pressure on the displaced surface),
            the support's constraint solved by this many modified-Newton steps on the linear
            stiffness (0: the linear model's forces). The linear model reads a firm press's
            normal force 5-12 % high and, at the E that fits it, the shear 15 % low
            (docs/evaluation.md, "Diagnosis of the torque and split errors").
        solver: ADMM SolverSettings, the core's (certified to 8e-4 of the objective). The
            support is read from the multipliers, and a looser certificate leaves them short
            of it on some frames: at 5e-3, support flips of 0.9-1.5 N (docs/evaluation.md,
            "The dual bound, the reported multipliers, and the estimator back at 8e-4").
    """

    material: Material = field(default_factory=lambda: DEFAULT_MATERIAL)
    k_f: float = ESTIMATOR_PARAMS["k_f"].default
    k_u: float = ESTIMATOR_PARAMS["k_u"].default
    k_const: float = ESTIMATOR_PARAMS["k_const"].default
    k_linear: float = ESTIMATOR_PARAMS["k_linear"].default
    k_peak: float = 0.5
    k_load: float = 0.25
    k_join: float = 2.0
    support_tol: float = ESTIMATOR_PARAMS["support_tol"].default
    peak_radius_m: float = ESTIMATOR_PARAMS["peak_radius_m"].default
    inflation_pa: float = SIM.bubble.gauge_pressure_pa
    ambient_pa: float = ESTIMATOR_PARAMS["ambient_pa"].default
    nonlinear_iterations: int = int(ESTIMATOR_PARAMS["nonlinear_iterations"].default)
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
        _validate.finite_scalar("k_peak", self.k_peak)
        _validate.finite_scalar("k_load", self.k_load)
        _validate.finite_scalar("k_join", self.k_join)
        for key in ("support_tol", "peak_radius_m", "nonlinear_iterations"):
            problem = ESTIMATOR_PARAMS[key].range.problem(getattr(self, key))
            if problem is not None:
                raise ValueError(f"{key} {problem}")
        _validate.positive("inflation_pa", self.inflation_pa)
        _validate.positive("ambient_pa", self.ambient_pa)

    def gauge_pressure(self, reference_pressure_pa: float | None) -> float:
        """Rest gauge pressure (Pa) from a reference pressure reading (``rest_gauge_pa``);
        ``inflation_pa`` when there is none or it is not positive."""
        gauge = rest_gauge_pa(reference_pressure_pa, self.ambient_pa)
        return gauge if gauge is not None else self.inflation_pa


def rest_gauge_pa(reading_pa: float | None, ambient_pa: float) -> float | None:
    """The rule every estimator uses for the rest gauge pressure (Pa): a reading above
    ``ABSOLUTE_PRESSURE_MIN`` is absolute (minus ``ambient_pa``), else already gauge; None
    when there is no finite reading or the gauge pressure is not positive."""
    if reading_pa is None or not np.isfinite(reading_pa):
        return None
    p = float(reading_pa)
    gauge = p - ambient_pa if p > ABSOLUTE_PRESSURE_MIN else p
    return gauge if gauge > 0 else None


#: The TOML ``[estimator]`` keys (daemon config, ``set_params``, ``bubble-rt calibrate``'s output)
#: and the EstimatorConfig field each one sets: (field, material field or None).
CONFIG_KEYS: dict[str, tuple[str, str | None]] = {
    k: (p.field, p.material) for k, p in ESTIMATOR_PARAMS.items()
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
            changes[name] = value if ESTIMATOR_PARAMS[key].range.integer else float(value)
        else:
            material[sub] = float(value)
    if material:
        changes["material"] = replace(config.material, **material)
    return changes


class ForceEstimator:
    """FEM estimator: inflated linear membrane, group lasso (ADMM core), refit on its support.

    Attributes:
        mesh: reference Mesh.
        config: EstimatorConfig in use.
        inflation_pa: rest gauge pressure the model is linearised about (Pa): the reference's
            (given here), else ``config.inflation_pa``.
        model: MembraneModel (rebuilt when the material or the rest pressure changes).
        solver: GroupLassoSolver (warm-started across calls).
    """

    def __init__(
        self, mesh: Mesh, config: EstimatorConfig | None = None, reference: Any = None
    ) -> None:
        self.mesh = mesh
        self.config = config or EstimatorConfig()
        self._interior = np.ascontiguousarray(mesh.interior, dtype=bool)
        #: the reference's pressure reading (Pa, absolute or gauge; None: no reference)
        self.reference_pressure_pa: float | None = getattr(reference, "pressure_pa", None)
        self._build(self.config.gauge_pressure(self.reference_pressure_pa))

    def _build(self, inflation_pa: float) -> None:
        from bubble_rt import _core

        cfg = self.config
        self.inflation_pa = float(inflation_pa)
        self.model = MembraneModel(self.mesh, cfg.material, self.inflation_pa)
        self.solver = GroupLassoSolver(self.model, cfg.k_f, cfg.k_u, cfg.solver)
        self._disc = _disc_matrix(self.mesh.vertices, cfg.peak_radius_m, self.model.areas)
        self._adjacency = self.mesh.adjacency()
        self._refit = _core._SupportRefit(
            self.model._core, np.ascontiguousarray(self.mesh.boundary, dtype=np.int32)
        )
        # the refit with the nonlinear membrane's forces (cpp/nonlinear_refit.h)
        self._nonlinear_refit = _core._NonlinearRefit(self._refit, self.model.nonlinear_core)

    def estimate(self, U: ArrayLike, dp: float) -> Estimate:
        """Estimate from displacements U (N x 3, m, mesh frame) and pressure change dp (Pa).

        Raises ValueError (naming the argument) on a wrong shape or NaN/inf; the solver's
        warm-start state is then left as it was.
        """
        t0 = time.perf_counter()
        res = self.solver.solve_frame(U, dp)
        t1 = time.perf_counter()
        U = np.asarray(U, dtype=np.float64)
        if res.info.status == "non_finite_input":
            support = np.zeros(self.mesh.n_nodes, bool)
            V, V_nl = U + res.dU, None
        else:
            support = self.support(res.dual)
            V, V_nl = self._refit_on(U, float(dp), support)
        V[self.mesh.boundary] = 0.0  # exact already; removes the -0.0 / round-off noise
        t2 = time.perf_counter()
        est = self._post(V, V_nl, float(dp), res.info, support)
        est.timings_ms = {
            "solve": 1e3 * (t1 - t0),
            "refit": 1e3 * (t2 - t1),
            "post": 1e3 * (time.perf_counter() - t2),
        }
        return est

    def support(self, dual: NDArray[np.float64]) -> NDArray[np.bool_]:
        """The support from the group lasso's multipliers: interior nodes whose multiplier is
        within ``support_tol`` of its bound, ``||y_i|| >= (1 - support_tol) k_f``.

        The lasso's own support (multiplier on its bound) tends to point loads: 2-5 nodes on
        every mesh, so its area fell like 1 / N. The multiplier field ``||y_i|| / k_f`` is
        mesh-independent (a Green's-function average of the weighted residual), so a fixed
        fraction of the bound gives a support of physical size; it also keeps the nodes of a
        first light touch whose multipliers have not yet reached the bound
        (docs/mesh-convergence.md)."""
        y = np.linalg.norm(np.asarray(dual, dtype=np.float64), axis=1)
        return np.ascontiguousarray(
            self._interior & (y >= (1.0 - self.config.support_tol) * self.config.k_f)
        )

    def _refit_on(
        self, U: NDArray[np.float64], dp: float, support: NDArray[np.bool_]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """The linear refit's V and, with ``nonlinear_iterations`` > 0 and a support, the
        nonlinear refit's V_nl (else None), C++ with the GIL released. The nonlinear refit is
        the smallest correction x of U whose GreenMembrane forces vanish off the support, from
        V = U + x0 by modified Newton steps on the linear stiffness K. Each step is the linear
        refit of a shifted U0 = U + K_ff^-1 q, q = F_nl(U + x) - F_lin(U + x): its raw forces
        are then F_nl(U + x) - K x, so its constraint is the linearisation of F_nl about U + x
        and its correction is still measured from U. Each step is taken as the fraction (1,
        1/2 or 1/4) of it that leaves the least nonlinear force off the support (full steps
        overshoot where a firm press stiffens the membrane). The support's system is factored
        once for the linear refit and every step; a step whose nonlinear forces off the
        support exceed twice the linear refit's (diverging) is not taken."""
        U = np.ascontiguousarray(U)
        steps = int(self.config.nonlinear_iterations)
        if steps == 0 or not support.any():
            return np.asarray(self._refit.refit(U, dp, support)), None
        V, V_nl, kept = self._nonlinear_refit.refit(U, dp, support, steps)
        # No step converged (far outside the membrane's range: centimetres of tracking noise,
        # a dent deeper than the bubble): the linear model's forces, which stay bounded.
        return np.asarray(V), (np.asarray(V_nl) if kept > 0 else None)

    def _post(
        self,
        V: NDArray[np.float64],
        V_nl: NDArray[np.float64] | None,
        dp: float,
        info: SolverInfo,
        support: NDArray[np.bool_],
    ) -> Estimate:
        """The estimate from the linear refit's V and, when there is one, the nonlinear
        refit's V_nl (its displacements and forces are reported)."""
        m = self.model
        if info.status == "non_finite_input":
            F = np.zeros_like(V)
        else:
            F = m.external_forces(V, dp)
        # The contact rule reads the linear refit's pressure: its thresholds (k_const, k_linear,
        # k_peak) were chosen on it, and on a firm press the nonlinear forces gather at the
        # dent's edge (k_peak then keeps 2-3 of 18 true contact nodes; mIoU 0.55 -> 0.46 on the
        # calibration seeds, docs/evaluation.md).
        p_rule = m.normal_pressure(F)
        if V_nl is not None:
            V = V_nl
            F = np.asarray(m.nonlinear_core.external_forces(V, dp))
        P = F / m.areas[:, None]
        p = m.normal_pressure(F)
        contact = m.contact_mask(p_rule, self.config.k_const, self.config.k_linear) & support
        label = np.full(contact.size, -1, np.int64)
        if contact.any():
            # the peak of a nodal pressure grows like 1 / spacing where the refit puts a line
            # load (the support's edge); over a disc of fixed radius it does not
            pd = self.disc_pressure(p_rule)
            force = np.where(contact, np.clip(p_rule, 0.0, None) * m.areas, 0.0)
            peak, label = load_regions(
                pd,
                support,
                self._adjacency,
                force,
                self.config.k_peak,
                self.config.k_load,
                self.config.k_join * (self.inflation_pa + dp),
            )
            contact &= pd >= self.config.k_peak * peak
            label[~contact] = -1
            fill_load_hulls(contact, label, support, self.mesh.vertices, m.normals)
        return Estimate(
            node_forces=F,
            contact_pressure=P,
            normal_pressure=p,
            contact=contact,
            net_force=m.net_force(F),
            displacements=V,
            info=info,
            support=support,
            rule_pressure=p_rule,
            patch_label=label,
        )

    def disc_pressure(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N,) Pa: the normal pressure ``p`` (N, Pa) averaged over each node's disc of
        ``peak_radius_m``: the normal force on the disc's nodes over their area."""
        return np.asarray(self._disc @ (p * self.model.areas), dtype=np.float64)

    def reconfigure(self, **changes: Any) -> None:
        """Change config fields in place (EstimatorConfig field names).

        k_f / k_u refactor the solver (milliseconds), k_const / k_linear / k_peak are free,
        solver settings are applied without rebuilding, material or ambient pressure rebuild
        K, the solver and the refit (tenths of a second; seconds on the fine mesh).
        """
        new = dataclasses.replace(self.config, **changes)  # validates
        if (new.material, new.ambient_pa, new.peak_radius_m) != (
            self.config.material,
            self.config.ambient_pa,
            self.config.peak_radius_m,
        ):
            self.config = new
            self._build(new.gauge_pressure(self.reference_pressure_pa))
        else:
            if (new.k_f, new.k_u) != (self.config.k_f, self.config.k_u):
                self.solver.set_weights(new.k_f, new.k_u)
            if new.solver != self.config.solver:
                self.solver.set_settings(new.solver)
        self.config = new


def _disc_matrix(
    vertices: NDArray[np.float64], radius: float, areas: NDArray[np.float64]
) -> sp.csr_matrix:
    """(N x N) sparse: row i averages a per-node force over the nodes within ``radius`` (m) of
    node i (i included), ``(D @ (p a))_i = sum_j p_j a_j / sum_j a_j`` over that disc."""
    from scipy.spatial import cKDTree

    X = np.asarray(vertices, dtype=np.float64)
    n = len(X)
    pairs = cKDTree(X).query_pairs(radius, output_type="ndarray") if radius > 0 else None
    if pairs is None or len(pairs) == 0:
        pairs = np.zeros((0, 2), dtype=np.int64)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    B = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return sp.csr_matrix(sp.diags(1.0 / (B @ np.asarray(areas, dtype=np.float64))) @ B)


def fill_load_hulls(
    contact: NDArray[np.bool_],
    label: NDArray[np.int64],
    support: NDArray[np.bool_],
    vertices: NDArray[np.float64],
    normals: NDArray[np.float64],
) -> None:
    """Mark, in place, the support nodes inside the convex hull of each load's contact nodes
    as that load's contact.

    A rigid indenter's contact on the membrane is convex where the indenter is, and the
    ``k_peak`` rule keeps a load's firmest nodes: around a curved indenter its middle, on a
    flat face its edges, where the bent membrane's line loads are (the face's middle carries
    only the gas's gauge pressure). The hull gives the face back its middle
    (docs/evaluation.md, "A load's contact is convex"). Loads of fewer than three contact
    nodes are left as they are; two loads (two pins) are filled each on its own.

    Computed in C++ (cpp/load_hulls.h); tests/test_estimator.py holds a Python reference.

    Args:
        contact: (N,) bool, the contact rule's nodes; updated.
        label: (N,) each contact node's load, -1 elsewhere; updated.
        support: (N,) bool, the nodes that carry force (the only ones filled).
        vertices: (N, 3) m, the untouched mesh.
        normals: (N, 3) outward unit normals; a load's hull is taken in the plane normal to
            its contact nodes' mean normal.
    """
    from bubble_rt import _core

    c, lab = _core._fill_load_hulls(
        np.ascontiguousarray(contact, dtype=bool),
        np.ascontiguousarray(label, dtype=np.int32),
        np.ascontiguousarray(support, dtype=bool),
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(normals, dtype=np.float64),
    )
    contact[:] = c
    label[:] = lab


def load_regions(
    pd: NDArray[np.float64],
    support: NDArray[np.bool_],
    adjacency: sp.csr_matrix,
    force: NDArray[np.float64],
    k_peak: float,
    k_load: float,
    join_pa: float = float("inf"),
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Each support node's load: the peak its contact threshold refers to, and its region.

    The support's nodes join from the highest disc pressure ``pd`` down (union-find over the
    mesh edges within the support). Where two regions meet at a node below ``k_peak`` times
    the lower region's peak, the two loads are apart in the contact rule's eyes; the lower one
    stays a load of its own (its nodes keep its peak and its label) when its core force (its
    nodes at ``k_peak`` of its peak) is at least ``k_load`` times the strongest core force so
    far (by then the main load's: two small regions meeting far from it stay under it).
    Otherwise, and where they meet above that level, they are one load: the rule compares
    with the higher peak. Two pins pressing apart meet far below either peak (a few per cent
    of them); the bumps around one dent, which split it into fragments under a single
    support-wide peak, meet near theirs or carry little force.

    Computed in C++ (cpp/load_regions.h); tests/test_estimator.py holds a Python reference.

    Args:
        pd: (N,) Pa, disc-averaged normal pressure.
        support: (N,) bool, the nodes that carry force.
        adjacency: N x N mesh edge adjacency (CSR).
        force: (N,) N, each node's normal force where it passes the paper's threshold, else 0.
        k_peak: the contact threshold's fraction of the load's peak (EstimatorConfig).
        k_load: the core force fraction that makes a load of its own (EstimatorConfig).
        join_pa: Pa; two regions meeting at a node whose ``pd`` is at least this are one
            load (EstimatorConfig.k_join times the gauge pressure; inf: never).

    Returns:
        ((N,) peak in Pa, inf off the support; (N,) region label, -1 off the support).
    """
    from bubble_rt import _core

    peak, label = _core._load_regions(
        np.ascontiguousarray(pd, dtype=np.float64),
        np.ascontiguousarray(support, dtype=bool),
        np.ascontiguousarray(adjacency.indptr, dtype=np.int32),
        np.ascontiguousarray(adjacency.indices, dtype=np.int32),
        np.ascontiguousarray(force, dtype=np.float64),
        float(k_peak),
        float(k_load),
        float(join_pa),
    )
    return np.asarray(peak, dtype=np.float64), np.asarray(label, dtype=np.int64)
