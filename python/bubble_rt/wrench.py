"""The contact wrench and patch geometry a force frame publishes (ForceFrame.net_torque,
ContactPatch normal / peak_pressure / torque / pressure_centroid).

* Net torque: ``tau = sum_i x_i x f_i`` over the non-rim nodes about the mesh origin, ``x_i``
  where the force acts: the mesh's vertex (the untouched membrane the daemon publishes as its
  Mesh) plus the node's measured displacement (the frame's node_displacements), so a
  subscriber recomputes it from a frame and the Mesh. Presses land 25-30 mm above the origin
  with the force pointing nearly through it, so the torque is a near cancellation and the
  few millimetres of a dent move it: at the untouched vertices the estimate read 0.15-0.25
  of the physical torque off on unseen simulator seeds, at the dented ones 0.04-0.08
  (docs/evaluation.md).
* Patches: the estimator's load regions (``Estimate.patch_label``: one load whose contact
  the rule keeps in pieces, the edges and corners of a flat face, is one patch; two pins are
  two), else the connected components of the contact mask over mesh edges. Each carries its
  area-weighted centroid and its normal-force-weighted centroid (``pressure_centroid``; the
  weights from the estimate's ``rule_pressure`` when it has one, the linear refit's pressure:
  the nonlinear forces gather at a dent's edge) over its contact nodes at their current
  positions (the mesh's vertices plus the measured
  displacements, when given), its area, the area-weighted mean outward normal of the mesh
  (unit) and the peak normal pressure over its contact nodes; and the force it carries, with
  that force's torque about ``centroid`` (at the same positions).
* The force a patch carries: its contact nodes' forces, plus, when the estimator's support
  (the nodes that carry force) is given, those of the support nodes connected to the patch
  through the support, each given to the patch with the nearest contact node. The contact
  rule keeps only a dent's firmest nodes (``k_peak``), so the contact nodes alone carry a
  share of the load (about 2/3 on simulated split-pin presses), while the support around them
  carries the rest; a support region with no contact node belongs to no patch.

Shared by the daemon (what it publishes) and the evaluation (what it scores), so both read the
same numbers.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt.io import protocol
from bubble_rt.mesh import Mesh


def net_torque(
    vertices: ArrayLike,
    node_forces: ArrayLike,
    interior: ArrayLike | None = None,
    displacements: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """(3,) N m: ``sum_i x_i x f_i`` over the ``interior`` nodes (all when None).

    Args:
        vertices: N x 3 node positions (m), mesh frame.
        node_forces: N x 3 forces on the nodes (N); non-finite entries count as zero.
        interior: (N,) bool, the non-rim nodes.
        displacements: N x 3 (m) added to ``vertices`` (non-finite entries count as zero).
    """
    x = _positions(vertices, displacements)
    f = np.nan_to_num(np.asarray(node_forces, dtype=np.float64).reshape(-1, 3))
    if f.shape != x.shape:
        raise ValueError(f"node_forces {f.shape} do not match vertices {x.shape}")
    if interior is not None:
        keep = np.asarray(interior, dtype=bool).reshape(-1)
        x, f = x[keep], f[keep]
    return np.asarray(np.cross(x, f).sum(axis=0), dtype=np.float64).reshape(3)


def _positions(vertices: ArrayLike, displacements: ArrayLike | None) -> NDArray[np.float64]:
    """N x 3 m: ``vertices`` plus ``displacements`` (None: none; non-finite ones count as 0)."""
    x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if displacements is None:
        return x
    u = np.nan_to_num(np.asarray(displacements, dtype=np.float64).reshape(-1, 3))
    if u.shape != x.shape:
        raise ValueError(f"displacements {u.shape} do not match vertices {x.shape}")
    return x + u


def _finite(a: ArrayLike) -> NDArray[np.float64]:
    """(N,) float64 of ``a`` with NaN and infinities as 0."""
    return np.nan_to_num(
        np.asarray(a, dtype=np.float64).reshape(-1), nan=0.0, posinf=0.0, neginf=0.0
    )


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 and np.isfinite(n) else np.zeros(3)


class PatchFinder:
    """Contact patches and the net torque of frames on one mesh (see the module docstring)."""

    def __init__(self, mesh: Mesh) -> None:
        self.adjacency = mesh.adjacency()
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.areas = mesh.lumped_areas()
        #: outward unit vertex normals (away from the camera), N x 3
        self.normals = np.asarray(mesh.vertex_normals(), dtype=np.float64)
        self.interior = np.asarray(mesh.interior, dtype=bool)

    def net_torque(
        self, node_forces: ArrayLike, displacements: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """(3,) N m about the mesh origin, over the non-rim nodes at the mesh's vertices
        plus ``displacements`` (N x 3 m; None: at the vertices)."""
        return net_torque(self.vertices, node_forces, self.interior, displacements)

    def net_torque_of(self, estimate: Any) -> NDArray[np.float64]:
        """:meth:`net_torque` of an estimate: its forces at its displaced nodes."""
        return self.net_torque(estimate.node_forces, estimate.displacements)

    def patches(
        self,
        contact: ArrayLike,
        node_forces: ArrayLike,
        displacements: ArrayLike | None = None,
        normal_pressure: ArrayLike | None = None,
        support: ArrayLike | None = None,
        weight_pressure: ArrayLike | None = None,
        label: ArrayLike | None = None,
    ) -> list[protocol.Patch]:
        """Patches of one frame, largest force first.

        Args:
            contact: (N,) bool contact mask.
            node_forces: N x 3 forces on the nodes (N).
            displacements: N x 3 measured displacements (m); positions are the mesh's
                vertices plus these (non-finite ones count as zero), else the vertices.
            normal_pressure: (N,) inward normal pressure (Pa); when None, ``-n . f / area``.
            support: (N,) bool, the nodes that carry force (the estimator's support); None
                or empty: each patch carries its contact nodes' forces only.
            weight_pressure: (N,) Pa, the pressure whose positive part times the lumped area
                weights ``pressure_centroid``; None or empty: the normal pressure.
            label: (N,) int, the patch of each contact node (``Estimate.patch_label``); None
                or empty: the contact's connected components.
        """
        from scipy.sparse.csgraph import connected_components

        idx = np.flatnonzero(np.asarray(contact, dtype=bool))
        if idx.size == 0:
            return []
        F = np.nan_to_num(np.asarray(node_forces, dtype=np.float64).reshape(-1, 3))
        if normal_pressure is None:
            with np.errstate(divide="ignore", invalid="ignore"):
                p = -np.einsum("ij,ij->i", self.normals, F) / self.areas
        else:
            p = np.asarray(normal_pressure, dtype=np.float64).reshape(-1)
        p = _finite(p)
        wp = p
        if weight_pressure is not None and np.size(weight_pressure) == p.size:
            wp = _finite(weight_pressure)
        pos = _positions(self.vertices, displacements)
        if label is not None and np.size(label) == len(self.vertices):
            _, labels = np.unique(np.asarray(label)[idx], return_inverse=True)
            n_comp = int(labels.max()) + 1
        else:
            sub = self.adjacency[idx][:, idx]
            n_comp, labels = connected_components(sub, directed=False)
        owner = self._load_owner(idx, labels, support)
        out = []
        for c in range(n_comp):
            nodes = idx[labels == c]
            a = self.areas[nodes]
            area = float(a.sum())
            w = a / area if area > 0 else np.full(len(nodes), 1.0 / len(nodes))
            x = pos[nodes]
            centroid = w @ x
            # The load's centre: normal force (positive pressure x area) weights.
            fn = np.clip(wp[nodes], 0.0, None) * a
            total = float(fn.sum())
            pc = (fn / total) @ x if total > 0 else centroid
            load = np.flatnonzero(owner == c)
            f = F[load]
            x_load = pos[load]
            out.append(
                protocol.Patch(
                    centroid=centroid,
                    area=area,
                    force=f.sum(axis=0),
                    nodes=nodes.astype(np.int64),
                    normal=_unit(a @ self.normals[nodes]),
                    peak_pressure=float(p[nodes].max()),
                    torque=np.cross(x_load - centroid, f).sum(axis=0),
                    pressure_centroid=pc,
                )
            )
        out.sort(key=lambda q: -float(np.linalg.norm(q.force)))
        return out

    def patches_of(self, estimate: Any) -> list[protocol.Patch]:
        """:meth:`patches` of an estimate (``bubble_rt.estimation.types.Estimate``): its
        contact, forces, displacements, normal pressure, support and rule pressure."""
        return self.patches(
            estimate.contact,
            estimate.node_forces,
            estimate.displacements,
            estimate.normal_pressure,
            estimate.support,
            weight_pressure=getattr(estimate, "rule_pressure", None),
            label=getattr(estimate, "patch_label", None),
        )

    def _load_owner(
        self, idx: NDArray[np.int64], labels: NDArray, support: ArrayLike | None
    ) -> NDArray[np.int64]:
        """(N,) patch index of each node whose force a patch carries (-1: none)."""
        n = len(self.vertices)
        owner = np.full(n, -1, np.int64)
        owner[idx] = labels
        sup = None if support is None else np.asarray(support, dtype=bool).reshape(-1)
        if sup is None or sup.shape != (n,):
            return owner
        from scipy.sparse.csgraph import connected_components

        load = np.flatnonzero(sup | (owner >= 0))
        _, comp = connected_components(self.adjacency[load][:, load], directed=False)
        for k in np.unique(comp):
            nodes = load[comp == k]
            seeds = nodes[owner[nodes] >= 0]
            if seeds.size == 0:
                continue  # force-carrying nodes with no contact: no patch's
            free = nodes[owner[nodes] < 0]
            if free.size:
                d = np.linalg.norm(
                    self.vertices[free, None, :] - self.vertices[None, seeds, :], axis=2
                )
                owner[free] = owner[seeds[np.argmin(d, axis=1)]]
        return owner
