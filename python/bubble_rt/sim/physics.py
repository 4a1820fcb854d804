"""Quasi-static physics of the simulated bubble: nonlinear membrane, enclosed air, contact.

Model (mesh frame, SI units: metres, newtons, pascals, joules):
- Membrane: incompressible neo-Hookean sheet on constant-strain triangles, strain energy per
  unit rest area ``W = mu t / 2 (|a|^2 + |b|^2 + 1 / |a x b|^2 - 3)`` with ``mu = E / 3`` and
  (a, b) the deformed images of an orthonormal rest frame of each triangle (C++,
  ``cpp/sim_membrane.*``). The rim (``Mesh.boundary``) is clamped. No bending.
- Air: isothermal ideal gas with a fixed amount in the bubble plus a chamber of volume Vc:
  ``P (V + Vc) = const``. As an energy ``P_atm (V - V0) - C log1p((V - V0) / (V0 + Vc))`` with
  ``C = P0 (V0 + Vc)``; its Hessian's dense rank-one part is applied with Sherman-Morrison.
  With compression off the gauge pressure stays constant (energy ``-p (V - V0)``).
- Contact: penalty ``k d^3 / 3`` on each node's penetration depth d into the indenter's SDF,
  and on sample points inside each triangle on their penetration beyond an allowance for the
  chord sag of a flat triangle (an indenter sharper than the mesh otherwise slips between the
  nodes; see ``ContactSettings``). Coulomb friction as the smoothed (IPC-style) dissipative
  potential ``mu_f lambda f0(|u_T|)`` on the tangential slip u_T of each contact point (node or
  sample) relative to the indenter since the previous step, with lambda (normal force) and the
  tangent plane lagged; the lag is refreshed by re-solving until lambda settles (so
  |f_T| <= mu_f f_N at every contact point).
- Equilibrium: Newton on the total energy with an Armijo line search; the exact Hessian is
  used while it is positive definite, else each element's Hessian is projected to PSD. A
  step that does not converge is retried in smaller substeps; if it still fails, the state
  says so and the simulation stays at the last converged equilibrium.

Sign conventions: contact forces are the forces the indenter applies on the membrane;
pressure forces are ``(P - P_atm) dV/dx`` (outward); rim reactions are the forces the base
applies on rim nodes. contact + pressure + rim reactions sum to zero at equilibrium.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.mesh import Mesh, MeshGeometry
from bubble_rt.sensor import SIM_BUBBLE
from bubble_rt.sim.indenters import Indenter

__all__ = [
    "MembraneMaterial",
    "GasSettings",
    "ContactSettings",
    "NewtonSettings",
    "SimState",
    "MembraneSim",
    "SimConvergenceError",
    "default_rest_mesh",
    "DEFAULT_REST_DOME_HEIGHT",
    "DEFAULT_CHAMBER_VOLUME",
    "DEFAULT_NODES",
    "PHYSICS_REVISION",
]

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Node count of the default simulation mesh.
DEFAULT_NODES = 2000
#: Dome height (m) of the stress-free rest shape (``bubble_rt.sensor.SIM_BUBBLE``).
DEFAULT_REST_DOME_HEIGHT = SIM_BUBBLE.rest_dome_height_m
#: Chamber volume (m^3) behind the membrane; calibrated so a ~4.5 N push with the round
#: indenter raises the pressure by about 0.45 kPa, as on the real sensor.
DEFAULT_CHAMBER_VOLUME = 1.45e-3

#: Revision of the physics' results, part of ``Scene.physics_key``: bump it whenever a change
#: here alters simulated states, so cached datasets are recomputed.
#: 2: contact at triangle surface samples; a failed step keeps the last converged state.
PHYSICS_REVISION = 2

#: Residual (N) below which Newton refreshes the lagged friction normal force in place.
_LAG_REFRESH_N = 1e-3
#: CG iterations (times ``NewtonSettings.cg_max_iterations``) allowed to undo the lumping of the
#: surface samples' coupling after a fresh factorisation: the lumping error has rank <= 6 per
#: loaded sample, and a lumped-only direction stalls Newton near equilibrium.
_COUPLED_CG_FACTOR = 4


class SimConvergenceError(RuntimeError):
    """Raised (only with ``NewtonSettings.strict``) when a step fails even after substeps."""


@dataclass(frozen=True)
class MembraneMaterial:
    """Membrane: Young's modulus ``E`` (Pa), thickness ``thickness`` (m); incompressible."""

    E: float = SIM_BUBBLE.youngs_modulus_pa
    thickness: float = SIM_BUBBLE.thickness_m

    def __post_init__(self) -> None:
        if not (self.E > 0 and self.thickness > 0):
            raise ValueError(f"E and thickness must be positive, got {self.E}, {self.thickness}")

    @property
    def mu_t(self) -> float:
        """Shear modulus times thickness (N/m), mu = E / 3."""
        return self.E / 3.0 * self.thickness


@dataclass(frozen=True)
class GasSettings:
    """Enclosed air: operating gauge pressure (Pa), ambient (Pa), chamber volume (m^3)."""

    gauge_pressure_pa: float = SIM_BUBBLE.gauge_pressure_pa
    atmospheric_pa: float = SIM_BUBBLE.ambient_pa
    chamber_volume_m3: float = DEFAULT_CHAMBER_VOLUME
    compressible: bool = True

    def __post_init__(self) -> None:
        if not self.gauge_pressure_pa > 0:
            raise ValueError(f"gauge pressure must be positive, got {self.gauge_pressure_pa}")
        if not self.atmospheric_pa > 0:
            raise ValueError(f"atmospheric pressure must be positive, got {self.atmospheric_pa}")
        if not self.chamber_volume_m3 >= 0:
            raise ValueError(f"chamber volume must be >= 0, got {self.chamber_volume_m3}")


@dataclass(frozen=True)
class ContactSettings:
    """Contact: Coulomb coefficient (None = frictionless), penalty k (N/m^2, energy
    k d^3 / 3 per node), friction smoothing slip ``slip_tolerance`` (m; below it contact sticks
    elastically), up to ``friction_passes`` re-solves refreshing the lagged normal force until
    it changes by less than ``lag_tolerance`` (relative to the largest).

    Surface samples: each triangle also carries ``surface_samples`` fixed material points at
    barycentric positions (the interior points of a regular barycentric grid, so the count
    must be 0, 1, 3, 6, 10, ...; 0 disables them). A sample at depth d inside the indenter has
    the penalty ``(k / surface_samples) e^3 / 3`` on its excess depth ``e = max(d - a, 0)``,
    with the allowance a = ``sample_allowance`` times the inradius of its triangle in the rest
    mesh. Between its nodes a flat triangle dips into a smooth indenter by the chord sag (about
    rc^2 / 2R at the centre, circumradius rc, indenter radius R); the allowance leaves that to
    the nodes, so contact with an indenter the mesh resolves is unchanged, while one sharper
    than the mesh, which would slip between the nodes, is held by the samples (0.5: a quarter
    of an equilateral triangle's circumradius, the sag on a sphere of radius 2 rc). A loaded
    sample has friction like a node (its own lagged normal force, tangent plane and slip);
    its forces act on the triangle's nodes by the barycentric weights.
    """

    friction: float | None = 0.5
    penalty: float = 2.0e8
    slip_tolerance: float = 2.0e-5
    friction_passes: int = 6
    lag_tolerance: float = 2.0e-3
    surface_samples: int = 3
    sample_allowance: float = 0.5

    def __post_init__(self) -> None:
        if self.friction is not None and not self.friction >= 0:
            raise ValueError(f"friction must be >= 0 or None, got {self.friction}")
        if not (self.penalty > 0 and self.slip_tolerance > 0 and self.friction_passes >= 1):
            raise ValueError("penalty, slip_tolerance and friction_passes must be positive")
        _barycentric_samples(self.surface_samples)  # validates the count
        if not self.sample_allowance >= 0:
            raise ValueError(f"sample_allowance must be >= 0, got {self.sample_allowance}")


def _barycentric_samples(n: int) -> Array:
    """Barycentric weights (n x 3) of the interior points of the smallest regular barycentric
    grid that has n of them (n = 0, 1, 3, 6, 10, ...)."""
    if n == 0:
        return np.zeros((0, 3))
    m = 3
    while (m - 1) * (m - 2) // 2 < n:
        m += 1
    if (m - 1) * (m - 2) // 2 != n:
        raise ValueError(f"surface_samples must be 0, 1, 3, 6, 10, ... (got {n})")
    pts = [(i, j, m - i - j) for i in range(1, m) for j in range(1, m - i)]
    return np.array(pts, dtype=np.float64) / m


@dataclass(frozen=True)
class NewtonSettings:
    """Equilibrium solver: stop when every free node's residual force is below
    ``tolerance_n`` (N); ``max_iterations`` per (sub)step; a failing step is halved up to
    ``max_halvings`` times; inflation in ``inflation_steps`` equal pressure increments;
    Newton steps are capped at ``max_step_m`` per node. ``strict`` raises instead of
    returning a state with ``converged=False``. With ``reuse_factorization`` a Newton system
    is first solved by conjugate gradients preconditioned with the previous factorisation
    (relative tolerance ``cg_tolerance``, at most ``cg_max_iterations``), and factorised anew
    only when that fails."""

    tolerance_n: float = 1.0e-8
    max_iterations: int = 40
    max_halvings: int = 5
    inflation_steps: int = 10
    max_step_m: float = 2.0e-3
    strict: bool = False
    reuse_factorization: bool = True
    cg_tolerance: float = 1.0e-7
    cg_max_iterations: int = 15


@dataclass(frozen=True, eq=False)
class SimState:
    """One equilibrium. Arrays are M x 3 (M simulation nodes) unless noted.

    vertices (m); triangles (T x 3); pressure_pa absolute (Pa); volume_m3 enclosed by the
    membrane and the rim plane; contact_forces (N) the indenter applies on the membrane;
    rim_reactions (N) the base applies on rim nodes (zero elsewhere); pressure_forces (N)
    gauge pressure on the nodes; contact (M,) bool: nodes penetrating the indenter or owning
    a surface sample deeper than its allowance (see ``ContactSettings``; the owner is the node
    with the largest barycentric weight, all tied ones for a centroid); converged; iterations
    (Newton, all substeps and friction passes); residual (N, largest free-node force
    imbalance); substeps used for this step; pose (4 x 4) of this equilibrium or None. A
    step that failed reports the last converged equilibrium (its vertices, forces and pose)
    with ``converged=False``.
    """

    vertices: Array
    triangles: NDArray[np.int32]
    pressure_pa: float
    volume_m3: float
    contact_forces: Array
    rim_reactions: Array
    pressure_forces: Array
    contact: NDArray[np.bool_]
    converged: bool
    iterations: int
    residual: float
    substeps: int
    pose: Array | None = None
    gauge_pressure_pa: float = 0.0
    elastic_energy_j: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def net_contact_force(self) -> Array:
        """Total force (3,) N the indenter applies on the membrane (all nodes; an indenter
        touching the clamped rim also loads rim nodes, see ``contact_forces``)."""
        return self.contact_forces.sum(axis=0)


def default_rest_mesh(
    n_nodes: int = DEFAULT_NODES,
    geometry: MeshGeometry | None = None,
    rest_dome_height_m: float = DEFAULT_REST_DOME_HEIGHT,
) -> Mesh:
    """The stress-free rest shape: the bubble footprint with a ``rest_dome_height_m`` dome
    (the default's, inflated to 5 kPa, gives the 30 mm operating dome)."""
    g = geometry or MeshGeometry()
    return Mesh.generate(n_nodes, replace(g, dome_height=rest_dome_height_m))


def _skew_free_pose(pose: Array) -> Array:
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite 4 x 4 transform, got shape {T.shape}")
    return T


def _interpolate_pose(a: Array, b: Array, s: float) -> Array:
    """Pose a fraction s of the way from a to b (linear translation, slerp rotation)."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
    out[:3, :3] = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
    out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
    return out


@dataclass
class _Problem:
    """Everything fixed during one Newton solve."""

    indenter: Indenter | None
    pose: Array | None
    gauge: float  # constant gauge pressure (Pa) when gas_C is None
    gas_C: float | None  # P0 (V0 + Vc) when the gas is sealed
    lam: Array | None = None  # lagged normal force per contact point (P,), friction only
    tangent: Array | None = None  # P x 3 x 3 lagged tangent projectors
    anchor: Array | None = None  # M x 3 node slip origins carried with the indenter


def _pose_of(prob: _Problem) -> Array:
    if prob.pose is None:
        raise ValueError("an indenter needs a pose")
    return prob.pose


@dataclass
class _Coupling:
    """Loaded surface samples at one configuration, for the exact Hessian product."""

    tri: NDArray[np.int64]  # K x 3 nodes of each sample's triangle
    w: Array  # K x 3 barycentric weights
    H: Array  # K x 3 x 3 Hessian in the sample point (penalty with SDF curvature, or friction)


def _joined(a: _Coupling | None, b: _Coupling | None) -> _Coupling | None:
    if a is None or b is None:
        return a or b
    return _Coupling(
        np.concatenate([a.tri, b.tri]), np.concatenate([a.w, b.w]), np.concatenate([a.H, b.H])
    )


def _scatter(idx: NDArray[np.int64], vals: Array, m: int) -> Array:
    """Sum vals (K x 3 x ...) into m rows by the node indices idx (K x 3)."""
    out = np.zeros((m,) + vals.shape[2:])
    np.add.at(out, idx.ravel(), vals.reshape((idx.size,) + vals.shape[2:]))
    return out


class MembraneSim:
    """Quasi-static simulation of the inflated bubble pressed by a rigid indenter.

    ``rest_mesh`` is the stress-free shape (see ``default_rest_mesh``); its rim
    (``boundary``) must lie in the plane z = 0. Call ``inflate()`` once, then ``solve`` for
    each indenter pose; each solve starts from the previous one (friction is path dependent).
    """

    def __init__(
        self,
        rest_mesh: Mesh,
        material: MembraneMaterial | None = None,
        gas: GasSettings | None = None,
        contact: ContactSettings | None = None,
        newton: NewtonSettings | None = None,
    ) -> None:
        from bubble_rt import _core

        self.rest_mesh = rest_mesh
        self.material = material or MembraneMaterial()
        self.gas = gas or GasSettings()
        self.contact_settings = contact or ContactSettings()
        self.newton = newton or NewtonSettings()
        rim = rest_mesh.boundary
        if len(rim) == 0:
            raise ValueError("rest mesh has no rim to clamp")
        if np.abs(rest_mesh.vertices[rim, 2]).max() > 1e-9:
            raise ValueError("the rim must lie in the plane z = 0 (mesh frame)")
        self._sys = _core._SimMembrane(
            rest_mesh.vertices, rest_mesh.triangles, rim, self.material.mu_t
        )
        self._free = rest_mesh.interior
        self._M = rest_mesh.n_nodes
        self._tri = np.asarray(rest_mesh.triangles, dtype=np.int64)
        self._bary = _barycentric_samples(self.contact_settings.surface_samples)
        self._sample_penalty = self.contact_settings.penalty / max(len(self._bary), 1)
        R = rest_mesh.vertices[self._tri]
        perimeter = np.linalg.norm(R - R[:, [1, 2, 0]], axis=2).sum(axis=1)
        area2 = np.linalg.norm(np.cross(R[:, 1] - R[:, 0], R[:, 2] - R[:, 0]), axis=1)
        self._sample_allowance = self.contact_settings.sample_allowance * area2 / perimeter
        pairs = np.sort(self._tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        self._edges = np.unique(pairs, axis=0)
        self._tri_cols = [np.ascontiguousarray(c) for c in self._tri.T]
        # Longest edge of the mesh at _edge_x: an upper bound for nearby x (see _longest_edge).
        self._edge_x: Array | None = None
        self._edge_max = 0.0
        # Contact points for friction: the nodes (weights 1, 0, 0), then sample s of triangle t
        # as point M + t S + s.
        S = len(self._bary)
        self._pt_nodes = np.concatenate(
            [np.repeat(np.arange(self._M)[:, None], 3, axis=1), np.repeat(self._tri, S, axis=0)]
        )
        self._pt_w = np.concatenate(
            [np.tile([1.0, 0.0, 0.0], (self._M, 1)), np.tile(self._bary, (len(self._tri), 1))]
        )
        self._n_points = len(self._pt_w)
        self._zero_blocks = np.zeros((self._M, 9))
        self._reference: SimState | None = None
        self._x_ref: Array | None = None
        self._V0 = 0.0
        self._C: float | None = None
        self._x = rest_mesh.vertices.copy()
        self._x_prev: Array | None = None  # state before the last step (for prediction)
        self._pose: Array | None = None
        self._lam = np.zeros(self._n_points)
        self._normals = np.zeros((self._n_points, 3))
        self._have_factor = False
        #: Counters for benchmarks: Newton iterations, fresh factorisations, CG iterations.
        self.stats = {"newton_iterations": 0, "factorizations": 0, "cg_iterations": 0, "solves": 0}
        self._last_prob = self._problem(None, None)

    # ------------------------------------------------------------------ public API
    @property
    def reference(self) -> SimState:
        """The inflated, untouched state (runs ``inflate()`` on first use)."""
        if self._reference is None:
            self.inflate()
        assert self._reference is not None
        return self._reference

    def inflate(self) -> SimState:
        """Inflate the rest shape to the operating gauge pressure (load stepping) and seal the
        air. Returns (and stores) the reference state."""
        X = self.rest_mesh.vertices
        x = X.copy()
        rise = np.ptp(X[:, 2])
        if rise < 1e-3 * np.ptp(X[:, 0]):
            # A flat sheet has no out-of-plane stiffness at rest: start from a small bulge.
            g = np.abs(X[:, :2]).max(axis=0)
            r2 = np.clip(1 - ((X[:, :2] / g) ** 2).sum(axis=1), 0, None)
            x[:, 2] += 0.05 * min(g) * r2
        p_t = self.gas.gauge_pressure_pa
        n = self.newton.inflation_steps
        iters = 0
        sub = 0
        ok = True
        res = 0.0
        done = 0.0
        # Pressure-controlled load stepping; halve an increment that fails.
        step = 1.0 / n
        while done < 1.0 - 1e-12:
            frac = min(1.0, done + step)
            prob = _Problem(None, None, p_t * frac, None)
            V_before, _ = self._sys.volume_grad(x)
            self._V0 = V_before
            x_try, ok_s, it, res = self._newton(x, prob)
            iters += it
            sub += 1
            if ok_s:
                x = x_try
                done = frac
                step = min(step * 1.5, 1.0 / n)
            else:
                step /= 2
                if step < 1.0 / (n * 2**self.newton.max_halvings):
                    ok = False
                    x = x_try
                    break
        V0, _ = self._sys.volume_grad(x)
        self._V0 = V0
        P0 = self.gas.atmospheric_pa + p_t
        self._C = P0 * (V0 + self.gas.chamber_volume_m3) if self.gas.compressible else None
        self._x = x
        self._x_ref = x.copy()
        self._x_prev = None
        self._pose = None
        self._lam = np.zeros(self._n_points)
        self._normals = np.zeros((self._n_points, 3))
        self._last_prob = self._problem(None, None)
        state = self._make_state(x, self._last_prob, ok, iters, res, sub)
        if not ok:
            self._report("inflation did not converge")
        self._reference = state
        return state

    def set_gas_scale(self, scale: float) -> None:
        """Scale the sealed gas's p V product (the amount times the temperature, n T / n0 T0)
        for the following solves: a warmer gas or a leak (``bubble_rt.sim.effects.gas_scale``).
        The membrane and the chamber then find their equilibrium at the new gas state (the
        dome's volume change included). No effect on an incompressible (constant-gauge) gas."""
        _ = self.reference
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"gas scale must be positive and finite, got {scale}")
        if self.gas.compressible:
            V0 = self._V0 + self.gas.chamber_volume_m3
            self._C = (self.gas.atmospheric_pa + self.gas.gauge_pressure_pa) * V0 * scale

    def reset_to_reference(self) -> None:
        """Forget the trajectory: the next solve starts from the untouched reference."""
        _ = self.reference
        assert self._x_ref is not None
        self._x = self._x_ref.copy()
        self._x_prev = None
        self._pose = None
        self._lam = np.zeros(self._n_points)
        self._normals = np.zeros((self._n_points, 3))
        self._last_prob = self._problem(None, None)

    def solve(self, indenter: Indenter, pose: Array) -> SimState:
        """Equilibrium with the indenter at ``pose`` (4 x 4 indenter -> mesh), starting from the
        previous solve. A failing step is retried in 2, 4, ... 2^max_halvings substeps; the
        state says how many were used and whether it converged. A step that fails even so
        leaves the simulation at the last converged equilibrium, which the state reports (with
        that equilibrium's pose and ``converged=False``); the next solve starts from there."""
        _ = self.reference
        pose = _skew_free_pose(pose)
        start_pose = self._pose if self._pose is not None else self._approach_pose(indenter, pose)
        saved = (
            self._x.copy(),
            self._lam.copy(),
            self._normals.copy(),
            self._x_prev,
            self._pose,
            self._last_prob,
        )
        total_iters = 0
        ok = False
        res = math.inf
        n_sub = 1
        for level in range(self.newton.max_halvings + 1):
            n_sub = 2**level
            self._restore(saved)
            for k in range(1, n_sub + 1):
                p_k = pose if k == n_sub else _interpolate_pose(start_pose, pose, k / n_sub)
                ok, it, res = self._step(indenter, p_k)
                total_iters += it
                if not ok:
                    break
            if ok:
                break
            log.info("step did not converge in %d substep(s); retrying with %d", n_sub, 2 * n_sub)
        if not ok:
            # The failed iterate is no equilibrium (a tunnelled or torn-up membrane would
            # poison every later step); staying at the converged one lets the next solve
            # bridge the gap from its pose in substeps.
            self._restore(saved)
        state = self._make_state(self._x, self._last_prob, ok, total_iters, res, n_sub)
        if not ok:
            self._report(f"step did not converge even in {n_sub} substeps (residual {res:.3g} N)")
            state = replace(state, notes=("not converged",))
        return state

    # ------------------------------------------------------------------ internals
    def _restore(
        self, saved: tuple[Array, Array, Array, Array | None, Array | None, _Problem]
    ) -> None:
        x, lam, normals, x_prev, pose, prob = saved
        self._x, self._lam, self._normals = x.copy(), lam.copy(), normals.copy()
        self._x_prev, self._pose, self._last_prob = x_prev, pose, prob

    def _report(self, msg: str) -> None:
        if self.newton.strict:
            raise SimConvergenceError(msg)
        log.warning(msg)

    def _problem(self, indenter: Indenter | None, pose: Array | None) -> _Problem:
        return _Problem(indenter, pose, self.gas.gauge_pressure_pa, self._C)

    def _approach_pose(self, indenter: Indenter, pose: Array) -> Array:
        """Where substeps start on a first contact: the pose backed off along the indenter's
        +z axis (presets press along their -z) until it no longer penetrates."""
        d, _ = indenter.distance(self._x, pose)
        back = max(0.0, -float(d.min())) + 1e-3
        out = pose.copy()
        out[:3, 3] += back * pose[:3, 2]
        return out

    def _step(self, indenter: Indenter, pose: Array) -> tuple[bool, int, float]:
        """One (sub)step from the current state to ``pose``, with friction lag passes."""
        x0 = self._x
        pose_prev = self._pose if self._pose is not None else pose
        prob = self._problem(indenter, pose)
        x = x0
        if self._x_prev is not None:
            # Predict: the previous increment repeated, if that lowers the energy.
            cand = x0 + (x0 - self._x_prev)
            if self._energy(cand, prob) < self._energy(x0, prob):
                x = cand
        use_friction = bool(self.contact_settings.friction)
        passes = self.contact_settings.friction_passes if use_friction else 1
        lam, normals = self._lam, self._normals
        iters = 0
        ok = False
        res = math.inf
        for _ in range(passes):
            prob = self._problem(indenter, pose)
            if use_friction:
                self._attach_friction(prob, lam, normals, x0, pose_prev, pose)
            x, ok, it, res = self._newton(x, prob)
            iters += it
            if not ok:
                break
            lam_new, normals = self._normal_forces(x, prob)
            scale = max(float(lam_new.max(initial=0.0)), 1e-12)
            used = prob.lam if prob.lam is not None else lam
            change = float(np.abs(lam_new - used).max(initial=0.0)) / scale
            lam = lam_new
            if change < self.contact_settings.lag_tolerance:
                break
        if ok:
            self._x_prev = x0
            self._x = x
            self._pose = pose
            self._lam, self._normals = lam, normals
            self._last_prob = prob
        return ok, iters, res

    def _attach_friction(
        self,
        prob: _Problem,
        lam: Array,
        normals: Array,
        x_prev: Array,
        pose_prev: Array,
        pose: Array,
    ) -> None:
        prob.lam = lam
        prob.tangent = np.eye(3)[None] - normals[:, :, None] * normals[:, None, :]
        # Where the previous contact points went with the indenter.
        D = pose @ np.linalg.inv(pose_prev)
        prob.anchor = x_prev @ D[:3, :3].T + D[:3, 3]

    def _normal_forces(self, x: Array, prob: _Problem) -> tuple[Array, Array]:
        """Normal contact force (P,) and SDF normal (P x 3) at every contact point: the nodes,
        then the surface samples (zero where a sample does not exceed its allowance)."""
        lam = np.zeros(self._n_points)
        normals = np.zeros((self._n_points, 3))
        if prob.indenter is None:
            return lam, normals
        d, g = prob.indenter.distance(x, _pose_of(prob))
        lam[: self._M] = self.contact_settings.penalty * np.maximum(-d, 0.0) ** 2
        normals[: self._M] = g
        ids, _, _, _, pen_s, ns = self._penetrating_samples(x, prob, d)
        lam[self._M + ids] = self._sample_penalty * pen_s**2
        normals[self._M + ids] = ns
        return lam, normals

    def _gas_terms(self, V: float, prob: _Problem) -> tuple[float, float, float]:
        """Gas energy (J), dE/dV (= -gauge pressure), d2E/dV2 at enclosed volume V."""
        dV = V - self._V0
        if prob.gas_C is None:
            return -prob.gauge * dV, -prob.gauge, 0.0
        Vc = self.gas.chamber_volume_m3
        C = prob.gas_C
        P_atm = self.gas.atmospheric_pa
        e = P_atm * dV - C * math.log1p(dV / (self._V0 + Vc))
        return e, P_atm - C / (V + Vc), C / (V + Vc) ** 2

    def _sdf_hessian(self, prob: _Problem, pts: Array) -> Array:
        """Hessian of the indenter's SDF (K x 3 x 3) at points by central differences of its
        gradient (works for any indenter)."""
        assert prob.indenter is not None
        Hd = np.empty((len(pts), 3, 3))
        if len(pts) == 0:
            return Hd
        h = 1e-6
        for j in range(3):
            off = np.zeros(3)
            off[j] = h
            gp = prob.indenter.distance(pts + off, _pose_of(prob))[1]
            gm = prob.indenter.distance(pts - off, _pose_of(prob))[1]
            Hd[:, :, j] = (gp - gm) / (2 * h)
        return np.asarray(0.5 * (Hd + Hd.transpose(0, 2, 1)))

    def _longest_edge(self, x: Array) -> float:
        """An upper bound of the mesh's longest edge at x: the last exact value plus twice the
        largest node displacement since, recomputed once that is 10 % loose."""
        if self._edge_x is not None:
            moved = float(np.sqrt(np.einsum("ij,ij->i", x - self._edge_x, x - self._edge_x).max()))
            if moved < 0.05 * self._edge_max:
                return self._edge_max + 2 * moved
        e = x[self._edges[:, 0]] - x[self._edges[:, 1]]
        self._edge_max = math.sqrt(float(np.einsum("ij,ij->i", e, e).max()))
        self._edge_x = x.copy()
        return self._edge_max

    def _penetrating_samples(
        self, x: Array, prob: _Problem, d: Array
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], Array, Array, Array, Array]:
        """Surface samples deeper in the indenter than their allowance: sample ids (K,; t S +
        s), nodes (K x 3), barycentric weights (K x 3), points (K x 3), excess depths (K,) and
        SDF gradients (K x 3); d: node distances.

        Runs at every energy evaluation, so the SDF is evaluated only at samples that can be
        that deep: it is 1-Lipschitz and p - x_i = sum_j w_j (x_j - x_i), so d(p) >= d_i -
        sum_j w_j |x_j - x_i| for each node i of the triangle."""
        S = len(self._bary)
        none = np.zeros((0, 3))
        empty = (np.zeros(0, np.int64), np.zeros((0, 3), np.int64), none, none, np.zeros(0), none)
        if S == 0 or prob.indenter is None:
            return empty
        c0, c1, c2 = self._tri_cols
        # Each bound is at least max_i d_i - (longest edge of the mesh): a cheap first cut.
        d_far = np.maximum(np.maximum(d[c0], d[c1]), d[c2])
        near = np.flatnonzero(d_far + self._sample_allowance < self._longest_edge(x))
        if len(near) == 0:
            return empty
        T = self._tri[near]
        X = x[T]
        L = np.sqrt(((X - X[:, [1, 2, 0]]) ** 2).sum(axis=2))  # edges 01, 12, 20
        dn = d[T]
        w = self._bary.T[:, None, :]  # 3 x 1 x S
        lower = np.maximum.reduce(
            [
                dn[:, 0, None] - w[1] * L[:, 0, None] - w[2] * L[:, 2, None],
                dn[:, 1, None] - w[0] * L[:, 0, None] - w[2] * L[:, 1, None],
                dn[:, 2, None] - w[0] * L[:, 2, None] - w[1] * L[:, 1, None],
            ]
        )
        t_idx, s_idx = np.nonzero(lower + self._sample_allowance[near, None] < 0)
        if len(t_idx) == 0:
            return empty
        w_k = self._bary[s_idx]
        pts = np.einsum("kj,kjd->kd", w_k, X[t_idx])
        ds, ns = prob.indenter.distance(pts, _pose_of(prob))
        ds = ds + self._sample_allowance[near[t_idx]]
        hit = ds < 0
        ids = near[t_idx[hit]] * S + s_idx[hit]
        return ids, T[t_idx[hit]], w_k[hit], pts[hit], -ds[hit], ns[hit]

    def _contact_terms(
        self, x: Array, prob: _Problem, need_grad: bool
    ) -> tuple[float, Array | None, Array | None, Array | None, _Coupling | None]:
        """Contact + friction energy, gradient (M x 3), PSD Hessian blocks (M x 3 x 3), the
        (indefinite) SDF-curvature part of the penalty Hessian (M x 3 x 3) and the loaded
        surface samples. A sample's Hessian H couples its triangle's nodes (w_i w_j H); the
        blocks hold it lumped (w_i H on node i) so that the factorisation stays per node, and
        ``_coupled_product`` adds the difference."""
        if prob.indenter is None:
            return 0.0, None, None, None, None
        cs = self.contact_settings
        k = cs.penalty
        pose = _pose_of(prob)
        d, n = prob.indenter.distance(x, pose)
        pen = np.maximum(-d, 0.0)
        e = k * float(np.sum(pen**3)) / 3.0
        _, tri, w, ps, pen_s, ns = self._penetrating_samples(x, prob, d)
        ks = self._sample_penalty
        e += ks * float(np.sum(pen_s**3)) / 3.0
        grad = blocks = curv = None
        coupling = None
        if need_grad:
            grad = -(k * pen**2)[:, None] * n
            blocks = (2 * k * pen)[:, None, None] * n[:, :, None] * n[:, None, :]
            curv = np.zeros_like(blocks)
            act = np.flatnonzero(pen > 0)
            # One batch of SDF evaluations for the curvature at nodes and samples alike.
            Hd = self._sdf_hessian(prob, np.concatenate([x[act], ps]))
            if len(act):
                curv[act] = -(k * pen[act] ** 2)[:, None, None] * Hd[: len(act)]
            if len(pen_s):
                M = self._M
                g_s = -(ks * pen_s**2)[:, None] * ns
                H_psd = (2 * ks * pen_s)[:, None, None] * ns[:, :, None] * ns[:, None, :]
                H_curv = -(ks * pen_s**2)[:, None, None] * Hd[len(act) :]
                wb = w[:, :, None, None]
                grad += _scatter(tri, w[:, :, None] * g_s[:, None, :], M)
                blocks += _scatter(tri, wb * H_psd[:, None], M)
                curv += _scatter(tri, wb * H_curv[:, None], M)
                coupling = _Coupling(tri, w, H_psd + H_curv)
        if prob.lam is not None and cs.friction:
            ef, gf, bf, cf = self._friction_terms(x, prob, need_grad)
            e += ef
            if need_grad:
                assert grad is not None and blocks is not None
                assert gf is not None and bf is not None
                grad += gf
                blocks += bf
                coupling = _joined(coupling, cf)
        return e, grad, blocks, curv, coupling

    def _friction_terms(
        self, x: Array, prob: _Problem, need_grad: bool
    ) -> tuple[float, Array | None, Array | None, _Coupling | None]:
        """Friction energy at the contact points with a lagged normal force, its gradient
        (M x 3), Hessian blocks (M x 3 x 3; a sample's lumped) and the samples' coupling."""
        cs = self.contact_settings
        assert prob.lam is not None and cs.friction
        act = np.flatnonzero(prob.lam > 0)
        if len(act) == 0:
            return 0.0, np.zeros((self._M, 3)), np.zeros((self._M, 3, 3)), None
        assert prob.tangent is not None and prob.anchor is not None
        idx, w = self._pt_nodes[act], self._pt_w[act]
        eps = cs.slip_tolerance
        P = prob.tangent[act]
        slip = np.einsum("kj,kjd->kd", w, x[idx] - prob.anchor[idx])
        u = np.einsum("nij,nj->ni", P, slip)
        y = np.linalg.norm(u, axis=1)
        small = y < eps
        f0 = np.where(small, y**2 / eps - y**3 / (3 * eps**2) + eps / 3, y)
        ml = cs.friction * prob.lam[act]
        e = float(np.sum(ml * f0))
        if not need_grad:
            return e, None, None, None
        f1_over_y = np.where(small, 2 / eps - y / eps**2, 1.0 / np.maximum(y, 1e-300))
        df1 = np.where(small, 2 / eps - 2 * y / eps**2, 0.0)
        g_p = (ml * f1_over_y)[:, None] * u
        uh = np.where(y[:, None] > 1e-14, u / np.maximum(y, 1e-300)[:, None], 0.0)
        uu = uh[:, :, None] * uh[:, None, :]
        H_p = ml[:, None, None] * (f1_over_y[:, None, None] * (P - uu) + df1[:, None, None] * uu)
        grad = _scatter(idx, w[:, :, None] * g_p[:, None, :], self._M)
        blocks = _scatter(idx, w[:, :, None, None] * H_p[:, None], self._M)
        on_sample = act >= self._M
        cpl = None
        if on_sample.any():
            cpl = _Coupling(idx[on_sample], w[on_sample], H_p[on_sample])
        return e, grad, blocks, cpl

    def _coupled_product(self, cpl: _Coupling, v: Array) -> Array:
        """(exact - lumped) sample Hessian times v (M x 3): node i of a sample gets
        w_i H (sum_j w_j v_j - v_i); rim rows zero."""
        V = v[cpl.tri]
        r = np.einsum("kj,kjd->kd", cpl.w, V)[:, None, :] - V
        out = _scatter(cpl.tri, cpl.w[:, :, None] * np.einsum("kde,kje->kjd", cpl.H, r), self._M)
        out[~self._free] = 0.0
        return out

    def _energy(self, x: Array, prob: _Problem) -> float:
        e = self._sys.energy(x)
        if not math.isfinite(e):
            return math.inf
        V, _ = self._sys.volume_grad(x)
        if prob.gas_C is not None and V + self.gas.chamber_volume_m3 <= 0:
            return math.inf
        e += self._gas_terms(V, prob)[0]
        e += self._contact_terms(x, prob, need_grad=False)[0]
        return e

    def _gradient(
        self, x: Array, prob: _Problem
    ) -> tuple[float, Array, Array, tuple[Array | None, Array | None, _Coupling | None]]:
        """Energy, gradient (rim rows zeroed), volume gradient, contact Hessian terms."""
        e, g = self._sys.energy_grad(x)
        V, dV = self._sys.volume_grad(x)
        eg, dE, _ = self._gas_terms(V, prob)
        ec, gc, bc, cc, cpl = self._contact_terms(x, prob, need_grad=True)
        g = g + dE * dV
        if gc is not None:
            g += gc
        g[~self._free] = 0.0
        return e + eg + ec, g, dV, (bc, cc, cpl)

    def _newton(self, x: Array, prob: _Problem) -> tuple[Array, bool, int, float]:
        """Minimise the total energy from x. Returns (x, converged, iterations, residual)."""
        ns = self.newton
        x = x.copy()
        E, g, dV, blocks = self._gradient(x, prob)
        res = float(np.abs(g).max())
        lag_settled = prob.lam is None
        for it in range(1, ns.max_iterations + 1):
            if prob.lam is not None and res < _LAG_REFRESH_N:
                # Refresh the lagged normal force inside the iteration once near equilibrium:
                # cheaper than re-solving from scratch after each lag update.
                lag_settled = self._lag_settled(x, prob)
                if not lag_settled:
                    E, g, dV, blocks = self._gradient(x, prob)
                    res = float(np.abs(g).max())
            if res <= ns.tolerance_n and lag_settled:
                return x, True, it - 1, res
            d, project = self._newton_direction(x, g, dV, blocks, res, prob)
            if d is None:
                return x, False, it, res
            big = float(np.linalg.norm(d, axis=1).max())
            if big > ns.max_step_m:
                d *= ns.max_step_m / big
            step = self._line_search(x, d, g, E, res, prob)
            if step is None:
                return x, False, it, res
            x, alpha = step
            self.stats["newton_iterations"] += 1
            E, g, dV, blocks = self._gradient(x, prob)
            res = float(np.abs(g).max())
            log.debug(
                "newton %d: residual %.3g N, step %.3g, projected %s", it, res, alpha, project
            )
        return x, res <= ns.tolerance_n and lag_settled, ns.max_iterations, res

    def _lag_settled(self, x: Array, prob: _Problem) -> bool:
        """Whether the lagged normal force is within the lag tolerance of the one at x; when
        it is not, ``prob`` takes the new one (and its tangent projectors)."""
        assert prob.lam is not None
        lam_new, normals = self._normal_forces(x, prob)
        scale = max(float(lam_new.max(initial=0.0)), 1e-12)
        settled = (
            float(np.abs(lam_new - prob.lam).max(initial=0.0)) / scale
            < self.contact_settings.lag_tolerance
        )
        if not settled:
            prob.lam = lam_new
            prob.tangent = np.eye(3)[None] - normals[:, :, None] * normals[:, None, :]
        return settled

    def _newton_direction(
        self, x: Array, g: Array, dV: Array, blocks: Any, res: float, prob: _Problem
    ) -> tuple[Array | None, bool]:
        """A descent direction (None: none found) and whether the Hessian had to be
        PSD-projected: CG preconditioned by the last factorisation, else a new factorisation
        of the exact Hessian, falling back to PSD-projected parts."""
        ns = self.newton
        V = float(self._sys.volume_grad(x)[0])
        _, dE, d2E = self._gas_terms(V, prob)
        bc, cc, cpl = blocks
        B_psd = self._zero_blocks if bc is None else bc.reshape(self._M, 9)
        B_all = B_psd if bc is None or cc is None else (bc + cc).reshape(self._M, 9)
        d = None
        project = False
        # Inexact Newton: a loose solve far from equilibrium, a tight one near it.
        rtol = min(1e-2, max(ns.cg_tolerance, 0.1 * res))
        if self._have_factor and ns.reuse_factorization:
            # The last factorisation preconditions CG on the current exact Hessian; it is
            # refreshed only when CG is slow or the Hessian is not positive definite.
            self._sys.assemble(x, dE, B_all, 0.0, False)
            d = self._pcg(g, dV, d2E, rtol, cpl)
            if d is not None and float(np.sum(d * g)) >= 0:
                d = None
        # Exact Hessian first; if it is not positive definite, PSD-projected parts.
        for project, shift, B in (
            (False, 0.0, B_all),
            (False, 0.0, B_psd),
            (True, 0.0, B_psd),
            (True, 1e-3 * self.material.mu_t, B_psd),
        ):
            if d is not None:
                break
            self._have_factor = False
            self.stats["factorizations"] += 1
            if not self._sys.factorize(x, dE, B, shift, project):
                continue
            if self._sys.nonpositive_pivots() > 0:
                continue
            self._have_factor = True
            d = self._direction(g, dV, d2E)
            if cpl is not None and B is B_all:
                # The factorisation has the sample coupling lumped; CG on the exact Hessian
                # restores the Newton step. Without it the lumped direction stays: its
                # matrix is positive definite here, so it still descends.
                n_cg = _COUPLED_CG_FACTOR * ns.cg_max_iterations
                d_exact = self._pcg(g, dV, d2E, rtol, cpl, n_cg)
                if d_exact is not None and float(np.sum(d_exact * g)) < 0:
                    d = d_exact
            if float(np.sum(d * g)) < 0:
                break
            d = None
        return d, project

    def _line_search(
        self, x: Array, d: Array, g: Array, E: float, res: float, prob: _Problem
    ) -> tuple[Array, float] | None:
        """Backtracking along d: Armijo on the energy, or, where the slope is below the
        energy's round-off, a decrease of the residual. (x + alpha d, alpha), or None."""
        slope = float(np.sum(d * g))
        alpha = 1.0
        if -slope < 1e-11 * max(abs(E), 1e-6):
            # Below the energy's round-off: judge steps by the residual instead.
            while alpha > 1e-3:
                x_new = x + alpha * d
                _, g_new, _, _ = self._gradient(x_new, prob)
                if float(np.abs(g_new).max()) < (1 - 0.25 * alpha) * res:
                    return x_new, alpha
                alpha *= 0.5
            return None
        while alpha > 1e-10:
            x_new = x + alpha * d
            if self._energy(x_new, prob) <= E + 1e-4 * alpha * slope:
                return x_new, alpha
            alpha *= 0.5
        return None

    def _pcg(
        self,
        g: Array,
        dV: Array,
        d2E: float,
        rtol: float,
        cpl: _Coupling | None = None,
        max_iterations: int | None = None,
    ) -> Array | None:
        """Solve (H + d2E u u^T) d = -g by CG preconditioned with the last factorisation
        (Sherman-Morrison for the rank-one part); H is the assembled matrix plus the surface
        samples' node coupling ``cpl``. None when it does not converge in ``max_iterations``
        (default ``cg_max_iterations``) or meets a direction of non-positive curvature."""
        sys = self._sys
        u = dV.copy()
        u[~self._free] = 0.0
        c = d2E
        w = sys.solve(u) if c else None
        self.stats["solves"] += 1 if c else 0
        den = 1.0 + c * float(np.sum(u * w)) if w is not None else 1.0

        def op(v: Array) -> Array:
            out = sys.multiply(v)
            if cpl is not None:
                out += self._coupled_product(cpl, v)
            if c:
                out += (c * float(np.sum(u * v))) * u
            return out

        def prec(r: Array) -> Array:
            z = sys.solve(r)
            self.stats["solves"] += 1
            if w is not None:
                z -= w * (c * float(np.sum(u * z)) / den)
            return z

        b = -g
        nb = float(np.sqrt(np.sum(b * b)))
        xk = np.zeros_like(b)
        r = b.copy()
        z = prec(r)
        p = z.copy()
        rz = float(np.sum(r * z))
        n_max = max_iterations or self.newton.cg_max_iterations
        for k in range(1, n_max + 1):
            Ap = op(p)
            pAp = float(np.sum(p * Ap))
            if not pAp > 0:
                return None
            a = rz / pAp
            xk += a * p
            r -= a * Ap
            if float(np.sqrt(np.sum(r * r))) <= rtol * nb:
                self.stats["cg_iterations"] += k
                return xk
            z = prec(r)
            rz_new = float(np.sum(r * z))
            p = z + (rz_new / rz) * p
            rz = rz_new
        self.stats["cg_iterations"] += n_max
        return None

    def _direction(self, g: Array, dV: Array, d2E: float) -> Array:
        """Newton direction with (A + c u u^T) d = -g via Sherman-Morrison."""
        y1 = self._sys.solve(-g)
        if d2E == 0.0:
            return y1
        u = dV.copy()
        u[~self._free] = 0.0
        y2 = self._sys.solve(u)
        return y1 - y2 * (d2E * float(np.sum(u * y1)) / (1.0 + d2E * float(np.sum(u * y2))))

    def _make_state(
        self, x: Array, prob: _Problem, ok: bool, iters: int, res: float, substeps: int
    ) -> SimState:
        e_el, g_el = self._sys.energy_grad(x)
        V, dV = self._sys.volume_grad(x)
        _, dE, _ = self._gas_terms(V, prob)
        gauge = -dE
        f_p = gauge * dV
        _, gc, _, _, _ = self._contact_terms(x, prob, need_grad=True)
        f_c = np.zeros_like(x) if gc is None else -gc
        rim = ~self._free
        reactions = np.zeros_like(x)
        reactions[rim] = g_el[rim] - f_p[rim] - f_c[rim]
        if prob.indenter is not None:
            d, _ = prob.indenter.distance(x, _pose_of(prob))
            contact = d < 0
            if len(self._bary):
                # A loaded sample marks the node whose lumped area it lies in (the rule of
                # GroundTruth.contact_mask), not its whole triangle: that would flag nodes
                # whose own area does not touch.
                _, tri, w, _, _, _ = self._penetrating_samples(x, prob, d)
                owner = w >= w.max(axis=1, keepdims=True) - 1e-12
                contact[tri[owner]] = True
        else:
            contact = np.zeros(self._M, bool)
        return SimState(
            vertices=x.copy(),
            triangles=self.rest_mesh.triangles,
            pressure_pa=self.gas.atmospheric_pa + gauge,
            volume_m3=V,
            contact_forces=f_c,
            rim_reactions=reactions,
            pressure_forces=f_p,
            contact=contact,
            converged=ok,
            iterations=iters,
            residual=res,
            substeps=substeps,
            pose=None if prob.pose is None else prob.pose.copy(),
            gauge_pressure_pa=gauge,
            elastic_energy_j=e_el,
        )
