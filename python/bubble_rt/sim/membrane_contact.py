"""Contact and friction energy terms of the simulated membrane (``bubble_rt.sim.physics``).

Penalty ``k d^3 / 3`` on the penetration depth of each node and surface sample into the
indenter's SDF, and the smoothed Coulomb friction potential on the contact points' tangential
slip with a lagged normal force (see ``ContactSettings`` and the model in
``bubble_rt.sim.physics``). Units: metres, newtons, joules (mesh frame); M nodes, T triangles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bubble_rt.mesh import Mesh
from bubble_rt.sim.membrane_state import (
    Array,
    ContactSettings,
    Problem,
    barycentric_samples,
    pose_of,
)


@dataclass
class Coupling:
    """Loaded surface samples at one configuration, for the exact Hessian product."""

    tri: NDArray[np.int64]  # K x 3 nodes of each sample's triangle
    w: Array  # K x 3 barycentric weights
    H: Array  # K x 3 x 3 Hessian in the sample point (penalty with SDF curvature, or friction)


def joined(a: Coupling | None, b: Coupling | None) -> Coupling | None:
    """Both couplings' samples in one (either may be None)."""
    if a is None or b is None:
        return a or b
    return Coupling(
        np.concatenate([a.tri, b.tri]), np.concatenate([a.w, b.w]), np.concatenate([a.H, b.H])
    )


def scatter(idx: NDArray[np.int64], vals: Array, m: int) -> Array:
    """Sum vals (K x 3 x ...) into m rows by the node indices idx (K x 3)."""
    out = np.zeros((m,) + vals.shape[2:])
    np.add.at(out, idx.ravel(), vals.reshape((idx.size,) + vals.shape[2:]))
    return out


class ContactModel:
    """The contact points of a rest mesh (nodes and triangle surface samples) and their
    energy terms under ``settings``; ``MembraneSim`` owns one."""

    def __init__(self, rest_mesh: Mesh, settings: ContactSettings) -> None:
        self.settings = settings
        self._free = rest_mesh.interior
        self._M = rest_mesh.n_nodes
        self._tri = np.asarray(rest_mesh.triangles, dtype=np.int64)
        self.bary = barycentric_samples(self.settings.surface_samples)
        self._sample_penalty = self.settings.penalty / max(len(self.bary), 1)
        R = rest_mesh.vertices[self._tri]
        perimeter = np.linalg.norm(R - R[:, [1, 2, 0]], axis=2).sum(axis=1)
        area2 = np.linalg.norm(np.cross(R[:, 1] - R[:, 0], R[:, 2] - R[:, 0]), axis=1)
        self._sample_allowance = self.settings.sample_allowance * area2 / perimeter
        pairs = np.sort(self._tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        self._edges = np.unique(pairs, axis=0)
        self._tri_cols = [np.ascontiguousarray(c) for c in self._tri.T]
        # Longest edge of the mesh at _edge_x: an upper bound for nearby x (see longest_edge).
        self._edge_x: Array | None = None
        self._edge_max = 0.0
        # Contact points for friction: the nodes (weights 1, 0, 0), then sample s of triangle t
        # as point M + t S + s.
        S = len(self.bary)
        self._pt_nodes = np.concatenate(
            [np.repeat(np.arange(self._M)[:, None], 3, axis=1), np.repeat(self._tri, S, axis=0)]
        )
        self._pt_w = np.concatenate(
            [np.tile([1.0, 0.0, 0.0], (self._M, 1)), np.tile(self.bary, (len(self._tri), 1))]
        )
        self.n_points = len(self._pt_w)

    def normal_forces(self, x: Array, prob: Problem) -> tuple[Array, Array]:
        """Normal contact force (P,) and SDF normal (P x 3) at every contact point: the nodes,
        then the surface samples (zero where a sample does not exceed its allowance)."""
        lam = np.zeros(self.n_points)
        normals = np.zeros((self.n_points, 3))
        if prob.indenter is None:
            return lam, normals
        d, g = prob.indenter.distance(x, pose_of(prob))
        lam[: self._M] = self.settings.penalty * np.maximum(-d, 0.0) ** 2
        normals[: self._M] = g
        ids, _, _, _, pen_s, ns = self.penetrating_samples(x, prob, d)
        lam[self._M + ids] = self._sample_penalty * pen_s**2
        normals[self._M + ids] = ns
        return lam, normals

    def sdf_hessian(self, prob: Problem, pts: Array) -> Array:
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
            gp = prob.indenter.distance(pts + off, pose_of(prob))[1]
            gm = prob.indenter.distance(pts - off, pose_of(prob))[1]
            Hd[:, :, j] = (gp - gm) / (2 * h)
        return np.asarray(0.5 * (Hd + Hd.transpose(0, 2, 1)))

    def longest_edge(self, x: Array) -> float:
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

    def penetrating_samples(
        self, x: Array, prob: Problem, d: Array
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], Array, Array, Array, Array]:
        """Surface samples deeper in the indenter than their allowance: sample ids (K,; t S +
        s), nodes (K x 3), barycentric weights (K x 3), points (K x 3), excess depths (K,) and
        SDF gradients (K x 3); d: node distances.

        Runs at every energy evaluation, so the SDF is evaluated only at samples that can be
        that deep: it is 1-Lipschitz and p - x_i = sum_j w_j (x_j - x_i), so d(p) >= d_i -
        sum_j w_j |x_j - x_i| for each node i of the triangle."""
        S = len(self.bary)
        none = np.zeros((0, 3))
        empty = (np.zeros(0, np.int64), np.zeros((0, 3), np.int64), none, none, np.zeros(0), none)
        if S == 0 or prob.indenter is None:
            return empty
        c0, c1, c2 = self._tri_cols
        # Each bound is at least max_i d_i - (longest edge of the mesh): a cheap first cut.
        d_far = np.maximum(np.maximum(d[c0], d[c1]), d[c2])
        near = np.flatnonzero(d_far + self._sample_allowance < self.longest_edge(x))
        if len(near) == 0:
            return empty
        T = self._tri[near]
        X = x[T]
        L = np.sqrt(((X - X[:, [1, 2, 0]]) ** 2).sum(axis=2))  # edges 01, 12, 20
        dn = d[T]
        w = self.bary.T[:, None, :]  # 3 x 1 x S
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
        w_k = self.bary[s_idx]
        pts = np.einsum("kj,kjd->kd", w_k, X[t_idx])
        ds, ns = prob.indenter.distance(pts, pose_of(prob))
        ds = ds + self._sample_allowance[near[t_idx]]
        hit = ds < 0
        ids = near[t_idx[hit]] * S + s_idx[hit]
        return ids, T[t_idx[hit]], w_k[hit], pts[hit], -ds[hit], ns[hit]

    def contact_terms(
        self, x: Array, prob: Problem, need_grad: bool
    ) -> tuple[float, Array | None, Array | None, Array | None, Coupling | None]:
        """Contact + friction energy, gradient (M x 3), PSD Hessian blocks (M x 3 x 3), the
        (indefinite) SDF-curvature part of the penalty Hessian (M x 3 x 3) and the loaded
        surface samples. A sample's Hessian H couples its triangle's nodes (w_i w_j H); the
        blocks hold it lumped (w_i H on node i) so that the factorisation stays per node, and
        ``coupled_product`` adds the difference."""
        if prob.indenter is None:
            return 0.0, None, None, None, None
        cs = self.settings
        k = cs.penalty
        pose = pose_of(prob)
        d, n = prob.indenter.distance(x, pose)
        pen = np.maximum(-d, 0.0)
        e = k * float(np.sum(pen**3)) / 3.0
        _, tri, w, ps, pen_s, ns = self.penetrating_samples(x, prob, d)
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
            Hd = self.sdf_hessian(prob, np.concatenate([x[act], ps]))
            if len(act):
                curv[act] = -(k * pen[act] ** 2)[:, None, None] * Hd[: len(act)]
            if len(pen_s):
                M = self._M
                g_s = -(ks * pen_s**2)[:, None] * ns
                H_psd = (2 * ks * pen_s)[:, None, None] * ns[:, :, None] * ns[:, None, :]
                H_curv = -(ks * pen_s**2)[:, None, None] * Hd[len(act) :]
                wb = w[:, :, None, None]
                grad += scatter(tri, w[:, :, None] * g_s[:, None, :], M)
                blocks += scatter(tri, wb * H_psd[:, None], M)
                curv += scatter(tri, wb * H_curv[:, None], M)
                coupling = Coupling(tri, w, H_psd + H_curv)
        if prob.lam is not None and cs.friction:
            ef, gf, bf, cf = self.friction_terms(x, prob, need_grad)
            e += ef
            if need_grad:
                assert grad is not None and blocks is not None
                assert gf is not None and bf is not None
                grad += gf
                blocks += bf
                coupling = joined(coupling, cf)
        return e, grad, blocks, curv, coupling

    def friction_terms(
        self, x: Array, prob: Problem, need_grad: bool
    ) -> tuple[float, Array | None, Array | None, Coupling | None]:
        """Friction energy at the contact points with a lagged normal force, its gradient
        (M x 3), Hessian blocks (M x 3 x 3; a sample's lumped) and the samples' coupling."""
        cs = self.settings
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
        grad = scatter(idx, w[:, :, None] * g_p[:, None, :], self._M)
        blocks = scatter(idx, w[:, :, None, None] * H_p[:, None], self._M)
        on_sample = act >= self._M
        cpl = None
        if on_sample.any():
            cpl = Coupling(idx[on_sample], w[on_sample], H_p[on_sample])
        return e, grad, blocks, cpl

    def coupled_product(self, cpl: Coupling, v: Array) -> Array:
        """(exact - lumped) sample Hessian times v (M x 3): node i of a sample gets
        w_i H (sum_j w_j v_j - v_i); rim rows zero."""
        V = v[cpl.tri]
        r = np.einsum("kj,kjd->kd", cpl.w, V)[:, None, :] - V
        out = scatter(cpl.tri, cpl.w[:, :, None] * np.einsum("kde,kje->kjd", cpl.H, r), self._M)
        out[~self._free] = 0.0
        return out
