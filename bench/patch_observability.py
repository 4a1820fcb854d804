"""Issue 18 item 4: what the nodes outside a contact patch can say about its size
(docs/mesh-convergence.md, "The patch's size is invisible outside it").

Loads a uniform disc of pressure, of radius 2 to 7 mm and the same total force, at the apex of
the estimator's linear membrane model (the 1500-node mesh, each sensor profile's rest
tension), solves K U = f with the rim clamped, and compares the displacements. Off the load a
taut membrane's displacement is a harmonic function of its load's moments: the force (log r),
its centroid (1 / r) and the traceless part of its second moment (cos 2 theta / r^2). An
isotropic patch's size is the trace, which no harmonic term carries, so the nodes outside the
patch see a point load of the same force whatever its size. Only the nodes inside see it.

The table gives, per radius: the patch area; how many nodes of each preset-sized mesh lie
inside it; the apex's displacement; and, against the 7 mm disc, over the nodes beyond ``r``,
the largest displacement change, and the same once the force is refitted to the 7 mm disc's
exterior (the scale in brackets), per newton.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/patch_observability.py
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
from bubble_rt.estimation.membrane import Material, MembraneModel
from bubble_rt.mesh import Mesh
from bubble_rt.sensor import PROFILES

RADII_M = (2e-3, 3.7e-3, 5e-3, 7e-3)
NODES = (227, 390, 749, 1500)
#: exterior rings: nodes farther than this from the load's centre (m)
BEYOND_M = (8e-3, 15e-3)
#: barycentric quadrature points per triangle edge (the disc's edge cuts triangles)
QUAD = 12


def _quadrature(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (T x Q x 3, m), weights (T x Q, m^2) and barycentric coordinates (Q x 3)."""
    n = QUAD
    up = [((i + 1 / 3) / n, (j + 1 / 3) / n) for i in range(n) for j in range(n - i)]
    down = [((i + 2 / 3) / n, (j + 2 / 3) / n) for i in range(n) for j in range(n - i - 1)]
    b = np.array(up + down)
    lam = np.c_[b, 1.0 - b.sum(1)]
    tri = mesh.vertices[mesh.triangles]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.einsum("qk,tkd->tqd", lam, tri), np.repeat(area[:, None] / len(lam), len(lam), 1), lam


def disc_load(model: MembraneModel, radius: float, force: float = 1.0) -> tuple[np.ndarray, float]:
    """Consistent nodal loads (N x 3, N) of a uniform inward pressure on the disc of ``radius``
    (m) about the apex's axis, scaled to ``force`` (N) in all, and the disc's area (m^2)."""
    pts, w, lam = _quadrature(model.mesh)
    w = w * (np.hypot(pts[..., 0], pts[..., 1]) <= radius)
    f = np.zeros((model.n_nodes, 3))
    for k in range(3):
        node = model.mesh.triangles[:, k]
        np.add.at(f, node, -(w @ lam[:, k])[:, None] * model.normals[node])
    return f * force / w.sum(), float(w.sum())


def main() -> None:
    meshes = {n: Mesh.generate(n) for n in NODES}
    inside = {n: np.hypot(*m.vertices[:, :2].T) for n, m in meshes.items()}  # axis distance
    mesh = meshes[NODES[-1]]
    r = np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1])
    apex = int(np.argmin(r))
    free = np.repeat(mesh.interior, 3)
    for name, prof in PROFILES.items():
        gauge = prof.bubble.rest_pressure_pa - prof.ambient_pa
        model = MembraneModel(
            mesh, Material(prof.youngs_modulus, prof.poisson, prof.thickness), gauge
        )
        solve = spla.factorized(model.stiffness[free][:, free].tocsc())
        U = {}
        for a in RADII_M:
            f, area = disc_load(model, a)
            u = np.zeros(3 * model.n_nodes)
            u[free] = solve(f.reshape(-1)[free])
            U[a] = (u.reshape(-1, 3), area)
        print(
            f"\n{name} profile: rest gauge {gauge / 1e3:.1f} kPa, T0 {model.tension:.0f} N/m, 1 N"
        )
        print(
            "| radius | area | nodes inside (227 / 390 / 749 / 1500) | apex |U| "
            + "".join(f"| beyond {b * 1e3:.0f} mm: max change, refitted " for b in BEYOND_M)
            + "|"
        )
        print("|---" * (4 + len(BEYOND_M)) + "|")
        ref = U[RADII_M[-1]][0]
        for a in RADII_M:
            u, area = U[a]
            counts = " / ".join(str(int((inside[n] <= a).sum())) for n in NODES)
            cells = ""
            for b in BEYOND_M:
                m = (r > b) & mesh.interior
                d = np.linalg.norm(u[m] - ref[m], axis=1)
                # the same exterior with the force refitted: a scale is a force, not a size
                s = float(np.vdot(u[m], ref[m]) / np.vdot(u[m], u[m]))
                d_fit = np.linalg.norm(s * u[m] - ref[m], axis=1)
                cells += f"| {d.max() * 1e3:.4f} mm, {d_fit.max() * 1e3:.4f} mm at x{s:.3f} "
            print(
                f"| {a * 1e3:.1f} mm | {area * 1e4:.2f} cm² | {counts} "
                f"| {np.linalg.norm(u[apex]) * 1e3:.3f} mm {cells}|"
            )


if __name__ == "__main__":
    main()
