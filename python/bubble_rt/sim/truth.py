"""Ground truth the simulator attaches to every frame (``Frame.truth``).

Sign conventions match the estimator: forces in newtons are the forces the indenter applies on
the membrane; the net force sums them over the non-rim simulation nodes. Positions are in the
mesh (sensor) frame, metres; pressure is absolute, pascals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from bubble_rt.mesh import Mesh

#: Force (N) from which a true patch is a touch: below it the truth marks no node for it (the
#: simulator's truth is exactly 0 N without indenter contact; a grazing first touch reads up to
#: a few hundredths of a newton). The evaluation's untouched frames are those below it.
TOUCH_N = 0.05
#: Barycentric sample points per triangle used by ``contact_mask`` (a triangular lattice of
#: interior points, none on a median, so each sample belongs to exactly one corner's third).
_LATTICE = 9


def _lattice_samples(n: int = _LATTICE) -> NDArray[np.float64]:
    pts = []
    for i in range(n):
        for j in range(n - i):
            # Centroids of the sub-triangles of an n-subdivision: interior, symmetric, no ties
            # with the medians except the centroid itself, which is dropped below.
            pts.append(((i + 1 / 3) / n, (j + 1 / 3) / n))
            if i + j < n - 1:
                pts.append(((i + 2 / 3) / n, (j + 2 / 3) / n))
    b = np.array(pts)
    lam = np.column_stack([b, 1.0 - b.sum(axis=1)])
    # Drop samples equidistant from two corners (a tie has no owner); keeps the split exact.
    srt = np.sort(lam, axis=1)
    keep = np.abs(srt[:, 2] - srt[:, 1]) > 1e-9
    return np.asarray(lam[keep])


def closest_points_on_triangles(
    p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Barycentric weights (K x 3) of the closest point on triangles (a, b, c) to points p
    (all K x 3); Ericson's region tests, vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = np.column_stack([1 - v - w, v, w])

        def setw(mask: NDArray[np.bool_], lam: NDArray[np.float64]) -> None:
            out[mask] = lam[mask]

        # Edge regions (later assignments take precedence over the face solution).
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        setw(m_bc, np.column_stack([0 * t_bc, 1 - t_bc, t_bc]))
        t_ac = d2 / (d2 - d6)
        m_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        setw(m_ac, np.column_stack([1 - t_ac, 0 * t_ac, t_ac]))
        t_ab = d1 / (d1 - d3)
        m_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        setw(m_ab, np.column_stack([1 - t_ab, t_ab, 0 * t_ab]))
    one = np.ones(len(p))
    zero = np.zeros(len(p))
    setw((d6 >= 0) & (d5 <= d6), np.column_stack([zero, zero, one]))
    setw((d3 >= 0) & (d4 <= d3), np.column_stack([zero, one, zero]))
    setw((d1 <= 0) & (d2 <= 0), np.column_stack([one, zero, zero]))
    return out


class SurfaceLocator:
    """Finds, for points near a triangle surface, the closest surface point as (triangle,
    barycentric weights). Shared by all frames of one simulation (the reference surface)."""

    def __init__(self, vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self._tree = cKDTree(self.vertices[self.triangles].mean(axis=1))
        self._cache: dict[bytes, tuple[NDArray, NDArray]] = {}

    def locate(self, points: NDArray[np.float64], k: int = 12) -> tuple[NDArray, NDArray]:
        """(triangle index (N,), barycentric weights (N x 3)) of the closest surface points."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        key = pts.tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        k = min(k, len(self.triangles))
        _, cand = self._tree.query(pts, k=k)
        cand = np.asarray(cand).reshape(len(pts), k)
        P = np.repeat(pts, k, axis=0)
        tri = self.triangles[cand.ravel()]
        V = self.vertices
        lam = closest_points_on_triangles(P, V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
        q = np.einsum("ij,ijk->ik", lam, V[tri])
        d2 = ((q - P) ** 2).sum(axis=1).reshape(len(pts), k)
        best = np.argmin(d2, axis=1)
        rows = np.arange(len(pts)) * k + best
        result = (cand.ravel()[rows], lam[rows])
        if len(self._cache) < 64:
            self._cache[key] = result
        return result


@dataclass(frozen=True)
class TruePatch:
    """One true contact patch: simulation node indices, force (3,) N the indenter applies on
    them, their force-weighted centroid (3,) m, ``sum |f_j| x_j / sum |f_j|`` at the nodes'
    current positions, and its area (m^2): the lumped areas of its nodes on the untouched
    simulation surface (the convention of an estimated patch's ``area``, on a finer mesh)."""

    nodes: NDArray[np.int64]
    force: NDArray[np.float64]
    centroid: NDArray[np.float64]
    area: float = float("nan")


@dataclass
class GroundTruth:
    """Exact state of one simulated frame.

    Attributes:
        indenter_pose: 4 x 4 indenter-to-mesh transform (m).
        net_force: (3,) N, force the indenter applies on the membrane, summed over non-rim nodes.
        node_forces: M x 3 N, contact force on each simulation node.
        pressure_pa: absolute gas pressure (Pa), before any sensor noise.
        sim_vertices: M x 3 current node positions (m).
        sim_reference_vertices: M x 3 node positions of the untouched inflated membrane (m).
        sim_triangles: T x 3 int32.
        contact: M bool, simulation nodes touching the indenter.
        converged: the physics step converged.
        interior: M bool, the non-rim simulation nodes (None: all), which the net force and
            torque sum over.
    """

    indenter_pose: NDArray[np.float64]
    net_force: NDArray[np.float64]
    node_forces: NDArray[np.float64]
    pressure_pa: float
    sim_vertices: NDArray[np.float64]
    sim_reference_vertices: NDArray[np.float64]
    sim_triangles: NDArray[np.int32]
    contact: NDArray[np.bool_]
    converged: bool = True
    locator: SurfaceLocator | None = field(default=None, repr=False, compare=False)
    interior: NDArray[np.bool_] | None = None

    def _interior(self) -> NDArray[np.bool_]:
        n = len(self.node_forces)
        return np.ones(n, bool) if self.interior is None else np.asarray(self.interior, bool)

    def net_torque(self, at_reference: bool = False) -> NDArray[np.float64]:
        """(3,) N m: true torque of the contact forces about the mesh origin, ``sum_j x_j x
        f_j`` over the non-rim simulation nodes at their current positions (the physical
        torque), or with ``at_reference`` at their untouched positions (the definition the
        daemon publishes: forces at the untouched mesh's nodes)."""
        keep = self._interior()
        x = self.sim_reference_vertices if at_reference else self.sim_vertices
        x = np.asarray(x, dtype=np.float64)[keep]
        f = np.asarray(self.node_forces, dtype=np.float64)[keep]
        return np.asarray(np.cross(x, f).sum(axis=0), dtype=np.float64).reshape(3)

    def patches(self) -> list[TruePatch]:
        """The true contact patches, largest force first: connected components (over the
        simulation triangles' edges) of the non-rim nodes that touch the indenter or carry a
        contact force, each with its force and force-weighted centroid."""
        from scipy.sparse.csgraph import connected_components

        from bubble_rt.mesh import edge_adjacency, lumped_areas

        f = np.asarray(self.node_forces, dtype=np.float64)
        mag = np.linalg.norm(f, axis=1)
        touching = (np.asarray(self.contact, dtype=bool) | (mag > 0)) & self._interior()
        idx = np.flatnonzero(touching)
        if idx.size == 0:
            return []
        A = edge_adjacency(self.sim_triangles, len(f))[idx][:, idx]
        n_comp, labels = connected_components(A, directed=False)
        x = np.asarray(self.sim_vertices, dtype=np.float64)
        areas = lumped_areas(np.asarray(self.sim_reference_vertices), self.sim_triangles)
        out = []
        for c in range(n_comp):
            nodes = idx[labels == c]
            w = mag[nodes]
            total = float(w.sum())
            if total <= 0:
                continue  # touching without load: no force to locate
            out.append(
                TruePatch(
                    nodes=nodes,
                    force=f[nodes].sum(axis=0),
                    centroid=(w / total) @ x[nodes],
                    area=float(areas[nodes].sum()),
                )
            )
        out.sort(key=lambda p: -float(np.linalg.norm(p.force)))
        return out

    def _locator(self) -> SurfaceLocator:
        if self.locator is None:
            self.locator = SurfaceLocator(self.sim_reference_vertices, self.sim_triangles)
        return self.locator

    def displace(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Current positions (N x 3, m) of material points given on the reference surface.

        Each point is matched to its closest point on the simulation's reference surface
        (triangle + barycentric weights); that material point's current position is the same
        barycentric combination of the current vertices. A point off the surface keeps its
        offset from the surface unchanged, so the map is exactly the identity at the reference.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tri, lam = self._locator().locate(pts)
        T = self.sim_triangles[tri]
        ref = np.einsum("ij,ijk->ik", lam, self.sim_reference_vertices[T])
        cur = np.einsum("ij,ijk->ik", lam, self.sim_vertices[T])
        return np.asarray(cur + (pts - ref))

    def contact_mask(self, mesh: Mesh) -> NDArray[np.bool_]:
        """Contact on another mesh's nodes (N bool), e.g. an estimator mesh on the reference.

        Rule: node i is in contact when more than half of its lumped area region (the third of
        every incident triangle nearest to i, i.e. where i's barycentric weight is the largest)
        lies in the simulation's contact region. The region is measured by a fixed lattice of
        sample points in every triangle, each weighted by the triangle's area; a sample lies in
        the contact region when the linear interpolation of the simulation nodes' 0/1 contact
        flags at its closest point on the simulation reference surface exceeds 0.5. Every
        true patch (``patches``) of ``TOUCH_N`` or more also marks the node nearest its
        force-weighted centre on the untouched surface: a patch smaller than half a node's
        region (a pin, one of two pins) would otherwise leave no node in contact under a load
        of newtons, and an estimate that marks the loaded node would score as a false contact.
        """
        V = np.asarray(mesh.vertices, dtype=np.float64)
        T = np.asarray(mesh.triangles, dtype=np.int64)
        if not self.contact.any():
            return np.zeros(len(V), bool)
        lam = _lattice_samples()
        S = len(lam)
        P = np.einsum("sk,tkd->tsd", lam, V[T]).reshape(-1, 3)
        tri, w = self._locator().locate(P)
        flag = self.contact.astype(np.float64)
        inside = (w * flag[self.sim_triangles[tri]]).sum(axis=1) > 0.5
        area = 0.5 * np.linalg.norm(
            np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1
        )
        owner = T[np.arange(len(T))[:, None], np.argmax(lam, axis=1)[None, :]].ravel()
        wt = np.repeat(area / S, S)
        total = np.bincount(owner, weights=wt, minlength=len(V))
        covered = np.bincount(owner, weights=wt * inside, minlength=len(V))
        with np.errstate(invalid="ignore", divide="ignore"):
            mask = covered > 0.5 * total
        x_ref = np.asarray(self.sim_reference_vertices, dtype=np.float64)
        f = np.linalg.norm(np.asarray(self.node_forces, dtype=np.float64), axis=1)
        centres = [
            (f[p.nodes] / f[p.nodes].sum()) @ x_ref[p.nodes]
            for p in self.patches()
            if np.linalg.norm(p.force) >= TOUCH_N
        ]
        if centres:
            mask[cKDTree(V).query(np.asarray(centres))[1]] = True
        return np.asarray(mask)
