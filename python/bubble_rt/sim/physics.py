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
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np

from bubble_rt.mesh import Mesh
from bubble_rt.sim.indenters import Indenter
from bubble_rt.sim.membrane_contact import ContactModel, Coupling
from bubble_rt.sim.membrane_linalg import pcg, sherman_morrison_direction
from bubble_rt.sim.membrane_state import (
    DEFAULT_CHAMBER_VOLUME,
    DEFAULT_NODES,
    DEFAULT_REST_DOME_HEIGHT,
    Array,
    ContactSettings,
    GasSettings,
    MembraneMaterial,
    NewtonSettings,
    Problem,
    SimConvergenceError,
    SimState,
    default_rest_mesh,
    interpolate_pose,
    pose_of,
    skew_free_pose,
)

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
        self._contact = ContactModel(rest_mesh, self.contact_settings)
        self._zero_blocks = np.zeros((self._M, 9))
        self._reference: SimState | None = None
        self._x_ref: Array | None = None
        self._V0 = 0.0
        self._C: float | None = None
        self._x = rest_mesh.vertices.copy()
        self._x_prev: Array | None = None  # state before the last step (for prediction)
        self._pose: Array | None = None
        self._lam = np.zeros(self._contact.n_points)
        self._normals = np.zeros((self._contact.n_points, 3))
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
            prob = Problem(None, None, p_t * frac, None)
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
        self._lam = np.zeros(self._contact.n_points)
        self._normals = np.zeros((self._contact.n_points, 3))
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
        self._lam = np.zeros(self._contact.n_points)
        self._normals = np.zeros((self._contact.n_points, 3))
        self._last_prob = self._problem(None, None)

    def solve(self, indenter: Indenter, pose: Array) -> SimState:
        """Equilibrium with the indenter at ``pose`` (4 x 4 indenter -> mesh), starting from the
        previous solve. A failing step is retried in 2, 4, ... 2^max_halvings substeps; the
        state says how many were used and whether it converged. A step that fails even so
        leaves the simulation at the last converged equilibrium, which the state reports (with
        that equilibrium's pose and ``converged=False``); the next solve starts from there."""
        _ = self.reference
        pose = skew_free_pose(pose)
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
                p_k = pose if k == n_sub else interpolate_pose(start_pose, pose, k / n_sub)
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
        self, saved: tuple[Array, Array, Array, Array | None, Array | None, Problem]
    ) -> None:
        x, lam, normals, x_prev, pose, prob = saved
        self._x, self._lam, self._normals = x.copy(), lam.copy(), normals.copy()
        self._x_prev, self._pose, self._last_prob = x_prev, pose, prob

    def _report(self, msg: str) -> None:
        if self.newton.strict:
            raise SimConvergenceError(msg)
        log.warning(msg)

    def _problem(self, indenter: Indenter | None, pose: Array | None) -> Problem:
        return Problem(indenter, pose, self.gas.gauge_pressure_pa, self._C)

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
            lam_new, normals = self._contact.normal_forces(x, prob)
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
        prob: Problem,
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

    def _gas_terms(self, V: float, prob: Problem) -> tuple[float, float, float]:
        """Gas energy (J), dE/dV (= -gauge pressure), d2E/dV2 at enclosed volume V."""
        dV = V - self._V0
        if prob.gas_C is None:
            return -prob.gauge * dV, -prob.gauge, 0.0
        Vc = self.gas.chamber_volume_m3
        C = prob.gas_C
        P_atm = self.gas.atmospheric_pa
        e = P_atm * dV - C * math.log1p(dV / (self._V0 + Vc))
        return e, P_atm - C / (V + Vc), C / (V + Vc) ** 2

    def _energy(self, x: Array, prob: Problem) -> float:
        e = self._sys.energy(x)
        if not math.isfinite(e):
            return math.inf
        V, _ = self._sys.volume_grad(x)
        if prob.gas_C is not None and V + self.gas.chamber_volume_m3 <= 0:
            return math.inf
        e += self._gas_terms(V, prob)[0]
        e += self._contact.contact_terms(x, prob, need_grad=False)[0]
        return e

    def _gradient(
        self, x: Array, prob: Problem
    ) -> tuple[float, Array, Array, tuple[Array | None, Array | None, Coupling | None]]:
        """Energy, gradient (rim rows zeroed), volume gradient, contact Hessian terms."""
        e, g = self._sys.energy_grad(x)
        V, dV = self._sys.volume_grad(x)
        eg, dE, _ = self._gas_terms(V, prob)
        ec, gc, bc, cc, cpl = self._contact.contact_terms(x, prob, need_grad=True)
        g = g + dE * dV
        if gc is not None:
            g += gc
        g[~self._free] = 0.0
        return e + eg + ec, g, dV, (bc, cc, cpl)

    def _newton(self, x: Array, prob: Problem) -> tuple[Array, bool, int, float]:
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

    def _lag_settled(self, x: Array, prob: Problem) -> bool:
        """Whether the lagged normal force is within the lag tolerance of the one at x; when
        it is not, ``prob`` takes the new one (and its tangent projectors)."""
        assert prob.lam is not None
        lam_new, normals = self._contact.normal_forces(x, prob)
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
        self, x: Array, g: Array, dV: Array, blocks: Any, res: float, prob: Problem
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
        self, x: Array, d: Array, g: Array, E: float, res: float, prob: Problem
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
        cpl: Coupling | None = None,
        max_iterations: int | None = None,
    ) -> Array | None:
        """``membrane_linalg.pcg`` on the current system with the samples' coupling ``cpl``
        (at most ``max_iterations``, default ``cg_max_iterations``)."""
        coupled = None if cpl is None else partial(self._contact.coupled_product, cpl)
        n_max = max_iterations or self.newton.cg_max_iterations
        return pcg(self._sys, g, dV, d2E, rtol, self._free, n_max, self.stats, coupled)

    def _direction(self, g: Array, dV: Array, d2E: float) -> Array:
        return sherman_morrison_direction(self._sys, g, dV, d2E, self._free)

    def _make_state(
        self, x: Array, prob: Problem, ok: bool, iters: int, res: float, substeps: int
    ) -> SimState:
        e_el, g_el = self._sys.energy_grad(x)
        V, dV = self._sys.volume_grad(x)
        _, dE, _ = self._gas_terms(V, prob)
        gauge = -dE
        f_p = gauge * dV
        _, gc, _, _, _ = self._contact.contact_terms(x, prob, need_grad=True)
        f_c = np.zeros_like(x) if gc is None else -gc
        rim = ~self._free
        reactions = np.zeros_like(x)
        reactions[rim] = g_el[rim] - f_p[rim] - f_c[rim]
        if prob.indenter is not None:
            d, _ = prob.indenter.distance(x, pose_of(prob))
            contact = d < 0
            if len(self._contact.bary):
                # A loaded sample marks the node whose lumped area it lies in (the rule of
                # GroundTruth.contact_mask), not its whole triangle: that would flag nodes
                # whose own area does not touch.
                _, tri, w, _, _, _ = self._contact.penetrating_samples(x, prob, d)
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
