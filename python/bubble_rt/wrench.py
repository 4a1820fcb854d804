"""The contact wrench and patch geometry a force frame publishes (ForceFrame.net_torque,
ContactPatch normal / peak_pressure / torque / pressure_centroid).

* Net torque: ``tau = sum_i x_i x f_i`` over the non-rim nodes, ``x_i`` the mesh's vertices
  (the untouched membrane the daemon publishes as its Mesh), about the mesh origin: a
  subscriber recomputes it from a frame's node_forces and the Mesh alone.
* Patches: connected components of the contact mask over mesh edges. Each carries its
  area-weighted centroid and its normal-force-weighted centroid (``pressure_centroid``) at the
  nodes' current positions (the mesh's vertices plus the measured displacements, when given),
  its area, force, the area-weighted mean outward normal of the mesh (unit), the peak normal
  pressure, and the torque of its forces about ``centroid`` at those same positions.

Shared by the daemon (what it publishes) and the evaluation (what it scores), so both read the
same numbers.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt.io import protocol
from bubble_rt.mesh import Mesh


def net_torque(
    vertices: ArrayLike, node_forces: ArrayLike, interior: ArrayLike | None = None
) -> NDArray[np.float64]:
    """(3,) N m: ``sum_i x_i x f_i`` over the ``interior`` nodes (all when None).

    Args:
        vertices: N x 3 node positions (m), mesh frame.
        node_forces: N x 3 forces on the nodes (N); non-finite entries count as zero.
        interior: (N,) bool, the non-rim nodes.
    """
    x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.nan_to_num(np.asarray(node_forces, dtype=np.float64).reshape(-1, 3))
    if f.shape != x.shape:
        raise ValueError(f"node_forces {f.shape} do not match vertices {x.shape}")
    if interior is not None:
        keep = np.asarray(interior, dtype=bool).reshape(-1)
        x, f = x[keep], f[keep]
    return np.asarray(np.cross(x, f).sum(axis=0), dtype=np.float64).reshape(3)


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

    def net_torque(self, node_forces: ArrayLike) -> NDArray[np.float64]:
        """(3,) N m about the mesh origin, over the non-rim nodes at the mesh's vertices."""
        return net_torque(self.vertices, node_forces, self.interior)

    def patches(
        self,
        contact: ArrayLike,
        node_forces: ArrayLike,
        displacements: ArrayLike | None = None,
        normal_pressure: ArrayLike | None = None,
    ) -> list[protocol.Patch]:
        """Patches of one frame, largest force first.

        Args:
            contact: (N,) bool contact mask.
            node_forces: N x 3 forces on the nodes (N).
            displacements: N x 3 measured displacements (m); positions are the mesh's
                vertices plus these (non-finite ones count as zero), else the vertices.
            normal_pressure: (N,) inward normal pressure (Pa); when None, ``-n . f / area``.
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
        p = np.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0)
        pos = self.vertices
        if displacements is not None:
            pos = pos + np.nan_to_num(np.asarray(displacements, dtype=np.float64).reshape(-1, 3))
        sub = self.adjacency[idx][:, idx]
        n_comp, labels = connected_components(sub, directed=False)
        out = []
        for c in range(n_comp):
            nodes = idx[labels == c]
            a = self.areas[nodes]
            area = float(a.sum())
            w = a / area if area > 0 else np.full(len(nodes), 1.0 / len(nodes))
            x = pos[nodes]
            centroid = w @ x
            # The load's centre: normal force (positive pressure x area) weights.
            fn = np.clip(p[nodes], 0.0, None) * a
            total = float(fn.sum())
            pc = (fn / total) @ x if total > 0 else centroid
            f = F[nodes]
            out.append(
                protocol.Patch(
                    centroid=centroid,
                    area=area,
                    force=f.sum(axis=0),
                    nodes=nodes.astype(np.int64),
                    normal=_unit(a @ self.normals[nodes]),
                    peak_pressure=float(p[nodes].max()),
                    torque=np.cross(x - centroid, f).sum(axis=0),
                    pressure_centroid=pc,
                )
            )
        out.sort(key=lambda q: -float(np.linalg.norm(q.force)))
        return out
