"""Linear plane-stress membrane model, backed by the C++ core (docs/method.md, "Inflated
membrane model").

Units: metres, pascals, newtons. Sign convention: ``F_ext(U, dp) = K U - dp * a_i * n_i`` is
the force the object applies on each node; normal pressure ``p_i = -n_i . F_i / a_i`` is
positive inward.

``MembraneModel(mesh, material, inflation_pa=p0)`` linearises the *inflated* membrane
consistently: K = K_material + K_geometric - K_load. The reference shape is held by a membrane
tension T0 against the rest gauge pressure p0; T0 is the uniform isotropic tension that best
balances p0 on the reference mesh (Young-Laplace, least squares over the interior nodes:
T0 dA/dx_i = p0 a_i n_i). K_geometric = T0 * (P1 Laplacian of each triangle, per coordinate)
is the stiffness of that tension against out-of-plane motion; K_load = d(p0 * area vector / 3)
/ dx is the change of the rest pressure's nodal forces as the surface moves and turns (not
symmetric). With p0 = 0 the model is the paper's (material stiffness only).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from bubble_rt import _validate
from bubble_rt.mesh import Mesh


@dataclass(frozen=True)
class Material:
    """Membrane material.

    Attributes:
        E: Young's modulus (Pa). Paper default 1.317 MPa (latex, calibrated).
        nu: Poisson's ratio (-), in (-1, 0.5]; 0.5 for incompressible rubber.
        thickness: membrane thickness (m), 0.65 mm.
    """

    E: float = 1.317e6
    nu: float = 0.5
    thickness: float = 0.65e-3

    def __post_init__(self) -> None:
        _validate.positive("E", self.E)
        _validate.positive("thickness", self.thickness)
        nu = _validate.finite_scalar("nu", self.nu)
        # What the formulas admit (the C++ core checks the same). The product accepts less from
        # a user, [0, 0.5] for rubber (estimation.params); tests use other units and values.
        if not -1.0 < nu <= 0.5:
            raise ValueError(f"nu must be in (-1, 0.5], got {nu}")


def _core():  # noqa: ANN202 - private extension module
    from bubble_rt import _core as core

    return core


def _triangle_gradients(
    V: NDArray[np.float64], T: NDArray[np.integer]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per triangle: area (T,), in-plane frame (T x 2 x 3: i_hat, j_hat) and the in-plane
    gradients of the three linear shape functions (T x 2 x 3, 1/m)."""
    x0, x1, x2 = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    c = np.cross(x1 - x0, x2 - x0)
    area = 0.5 * np.linalg.norm(c, axis=1)
    k = c / (2.0 * area[:, None])
    i = (x1 - x0) / np.linalg.norm(x1 - x0, axis=1)[:, None]
    j = np.cross(k, i)
    a1, b1 = ((x1 - x0) * i).sum(1), ((x1 - x0) * j).sum(1)
    a2, b2 = ((x2 - x0) * i).sum(1), ((x2 - x0) * j).sum(1)
    det = a1 * b2 - a2 * b1
    G = np.zeros((len(T), 2, 3))
    G[:, 0, 1], G[:, 0, 2] = b2 / det, -b1 / det
    G[:, 1, 1], G[:, 1, 2] = -a2 / det, a1 / det
    G[:, :, 0] = -G[:, :, 1] - G[:, :, 2]
    return area, np.stack([i, j], axis=1), G


def inflation_tension(mesh: Mesh, gauge_pressure_pa: float) -> float:
    """Uniform membrane tension T0 (N/m) that holds the reference mesh against the rest gauge
    pressure: the whole cap's force balance (Young-Laplace summed over the interior nodes,
    T0 sum_i dA/dx_i = p0 sum_i a_i n_i, least squares over the 3 components).

    Summed, the tension's pull telescopes to the rim (the interior's sum of dA/dx_i is minus
    the rim's), so T0 does not depend on the node count nor on noise in a mesh fitted to a
    measured surface. A per-node least squares does: the fitted vertices' noise enters the
    discrete curvature as noise / spacing^2, which inflates sum |dA/dx_i|^2 and biased T0 low
    as the mesh refines (579 / 490 / 272 / 169 N/m on the real press's 227 / 390 / 749 /
    1500-node fitted meshes, against 641 / 645 / 648 / 654 N/m summed;
    docs/mesh-convergence.md)."""
    V = np.asarray(mesh.vertices, dtype=np.float64)
    T = np.asarray(mesh.triangles)
    area, frame, G = _triangle_gradients(V, T)
    grad_area = np.zeros_like(V)  # d(total area)/dx: the nodal pull of a unit tension
    area_vec = np.zeros_like(V)  # consistent a_i n_i: a third of each triangle's area vector
    normal = np.cross(frame[:, 0], frame[:, 1])
    for a in range(3):
        np.add.at(grad_area, T[:, a], area[:, None] * (G[:, :, a, None] * frame).sum(axis=1))
        np.add.at(area_vec, T[:, a], area[:, None] * normal / 3.0)
    interior = mesh.interior
    g, b = grad_area[interior].sum(axis=0), area_vec[interior].sum(axis=0)
    return float(gauge_pressure_pa) * float(g @ b / (g @ g))


def coordinatewise_stiffness(T: NDArray, blocks: NDArray, n_nodes: int) -> sp.csr_matrix:
    """Per-triangle node-node blocks ``blocks`` (T x 3 x 3, N/m) acting on each coordinate
    alike (``blocks (x) I_3``) summed into a 3N x 3N stiffness (node-major dofs, scipy CSR)."""
    rows, cols, vals = [], [], []
    for a in range(3):
        for b in range(3):
            for d in range(3):
                rows.append(3 * T[:, a] + d)
                cols.append(3 * T[:, b] + d)
                vals.append(blocks[:, a, b])
    shape = (3 * n_nodes, 3 * n_nodes)
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape
    )


def inflation_stiffness(mesh: Mesh, gauge_pressure_pa: float) -> tuple[sp.csr_matrix, float]:
    """(K_geometric - K_load, T0): the inflation terms of the linearised membrane (3N x 3N,
    N/m, scipy CSR) and the tension T0 (N/m) from :func:`inflation_tension`."""
    p0 = _validate.finite_scalar("gauge_pressure_pa", gauge_pressure_pa)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    T = np.asarray(mesh.triangles)
    n = len(V)
    tension = inflation_tension(mesh, p0)
    area, _, G = _triangle_gradients(V, T)
    lap = (area * tension)[:, None, None] * np.einsum("tka,tkb->tab", G, G)  # T x 3 x 3
    rows, cols, vals = [], [], []
    # Load stiffness: the nodal force of p0 on a triangle is p0 (x1 - x0) x (x2 - x0) / 6 on
    # each corner; its derivative by x_k is p0 / 6 [x_{k+2} - x_{k+1}]_x. Subtracted.
    X = [V[T[:, m]] for m in range(3)]
    for k in range(3):
        e = X[(k + 2) % 3] - X[(k + 1) % 3]
        skew = np.zeros((len(T), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = -e[:, 2], e[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = e[:, 2], -e[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -e[:, 1], e[:, 0]
        for j in range(3):
            for r in range(3):
                for c in range(3):
                    rows.append(3 * T[:, j] + r)
                    cols.append(3 * T[:, k] + c)
                    vals.append(-(p0 / 6.0) * skew[:, r, c])
    load = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n)
    )
    return coordinatewise_stiffness(T, lap, n) + load, tension


class GreenMembrane:
    """The inflated membrane of :class:`MembraneModel` with its geometric nonlinearity kept:
    the same constants (E, nu, thickness, rest tension T0, rest gauge pressure p0), the
    Green-Lagrange strain instead of the linear one, and the pressure acting on the displaced
    surface (docs/method.md, "Geometric nonlinearity (the refit's forces)").

    Per triangle (reference area A, in-plane gradients g_a of the linear shape functions, the
    deformation gradient F = sum_a x_a g_a^T, 3 x 2), the second Piola-Kirchhoff tension is
    ``S = T0 I + C : E`` with ``E = (F^T F - I) / 2`` and C the plane-stress law of
    :class:`Material` times the thickness; node a's internal force is ``A F S g_a``. A pressure
    p on a triangle puts ``p (x1 - x0) x (x2 - x0) / 6`` on each corner. The force the object
    applies on the nodes is

        F_ext(U, dp) = [f_int(X + U) - f_int(X)] - [f_p(X + U, p0 + dp) - f_p(X, p0)],

    whose linearisation about U = 0 is MembraneModel's ``K U - dp a n`` (material, geometric
    and load stiffness; the pressure change on the consistent rather than the lumped nodal
    normals). This NumPy class is the model's reference definition; the estimator evaluates
    the same forces in C++ (``cpp/green_membrane.h``, :attr:`MembraneModel.nonlinear_core`,
    equal to round-off: tests/test_membrane.py).
    """

    def __init__(self, mesh: Mesh, material: Material, inflation_pa: float, tension: float) -> None:
        V = np.asarray(mesh.vertices, dtype=np.float64)
        T = np.asarray(mesh.triangles)
        self._V, self._T = V, T
        self.p0 = float(inflation_pa)
        self.tension = float(tension)
        area, _, G = _triangle_gradients(V, T)
        self._AG = area[:, None, None] * G  # T x 2 x 3
        self._G = G
        nu = float(material.nu)
        self._nu = nu
        self._c = float(material.E) * float(material.thickness) / (1.0 - nu * nu)
        nt = len(T)
        # corner (t, a) -> node T[t, a]: sums per-corner forces (3 nt x 3) into nodes
        self._gather = sp.csr_matrix(
            (np.ones(3 * nt), (T.reshape(-1), np.arange(3 * nt))), shape=(len(V), 3 * nt)
        )
        self._f0 = self._internal(V) - self._pressure(V, self.p0)

    def _internal(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        P = x[self._T]  # T x 3 corners x 3
        G = self._G
        f1 = (P * G[:, 0, :, None]).sum(axis=1)  # dx/dxi_1 (T x 3)
        f2 = (P * G[:, 1, :, None]).sum(axis=1)
        e11 = 0.5 * ((f1 * f1).sum(axis=1) - 1.0)
        e22 = 0.5 * ((f2 * f2).sum(axis=1) - 1.0)
        e12 = 0.5 * (f1 * f2).sum(axis=1)
        c, nu = self._c, self._nu
        s11 = self.tension + c * (e11 + nu * e22)
        s22 = self.tension + c * (e22 + nu * e11)
        s12 = c * (1.0 - nu) * e12
        t1 = s11[:, None] * f1 + s12[:, None] * f2  # F S, column 1 (T x 3)
        t2 = s12[:, None] * f1 + s22[:, None] * f2
        AG = self._AG
        fa = t1[:, None, :] * AG[:, 0, :, None] + t2[:, None, :] * AG[:, 1, :, None]
        return np.asarray(self._gather @ fa.reshape(-1, 3))

    def _pressure(self, x: NDArray[np.float64], p: float) -> NDArray[np.float64]:
        T = self._T
        c = np.cross(x[T[:, 1]] - x[T[:, 0]], x[T[:, 2]] - x[T[:, 0]]) * (p / 6.0)
        return np.asarray(self._gather @ np.repeat(c, 3, axis=0))

    def external_forces(self, U: ArrayLike, dp: float) -> NDArray[np.float64]:
        """F_ext(U, dp) (N x 3, N) for displacements U (N x 3, m) and pressure change dp (Pa)."""
        x = self._V + np.asarray(U, dtype=np.float64)
        return self._internal(x) - self._pressure(x, self.p0 + float(dp)) - self._f0


class MembraneModel:
    """Constant-strain-triangle membrane of a mesh, built once per mesh and material.

    Attributes:
        mesh: the reference (inflated, untouched) mesh.
        material: the Material used.
        inflation_pa: rest gauge pressure p0 (Pa) the model is linearised about (0: the
            paper's uninflated model).
        tension: inflation tension T0 (N/m; 0 when inflation_pa is 0).
        areas: (N,) lumped areas a_i (m^2), a third of each incident triangle.
        normals: (N, 3) area-weighted outward unit normals.
        area_normals: (N, 3) a_i * n_i (m^2), the force per pascal of pressure.
    """

    def __init__(
        self, mesh: Mesh, material: Material | None = None, inflation_pa: float = 0.0
    ) -> None:
        self.mesh = mesh
        self.material = material or Material()
        self.inflation_pa = _validate.finite_scalar("inflation_pa", inflation_pa)
        if self.inflation_pa < 0:
            raise ValueError(f"inflation_pa must be >= 0, got {self.inflation_pa}")
        m = self.material
        self._core = _core()._Membrane(
            np.ascontiguousarray(mesh.vertices, dtype=np.float64),
            np.ascontiguousarray(mesh.triangles, dtype=np.int32),
            float(m.E),
            float(m.nu),
            float(m.thickness),
        )
        self.areas: NDArray[np.float64] = _readonly(self._core.areas)
        self.normals: NDArray[np.float64] = _readonly(self._core.normals)
        self.area_normals: NDArray[np.float64] = _readonly(self._core.area_normals)
        self._interior = np.ascontiguousarray(mesh.interior, dtype=bool)
        self.tension = 0.0
        if self.inflation_pa > 0:
            dK, self.tension = inflation_stiffness(mesh, self.inflation_pa)
            self._core.add_stiffness(sp.csc_matrix(dK))

    @property
    def n_nodes(self) -> int:
        return int(self.areas.shape[0])

    @cached_property
    def nonlinear(self) -> GreenMembrane:
        """The same membrane with its geometric nonlinearity (:class:`GreenMembrane`)."""
        return GreenMembrane(self.mesh, self.material, self.inflation_pa, self.tension)

    @cached_property
    def nonlinear_core(self) -> Any:
        """The C++ twin of :attr:`nonlinear` (private ``_core._GreenMembrane``: the same
        forces to round-off, ``external_forces(U, dp)`` on C-contiguous float64 N x 3 U)."""
        m = self.material
        return _core()._GreenMembrane(
            np.ascontiguousarray(self.mesh.vertices, dtype=np.float64),
            np.ascontiguousarray(self.mesh.triangles, dtype=np.int32),
            float(m.E),
            float(m.nu),
            float(m.thickness),
            float(self.tension),
            float(self.inflation_pa),
        )

    @cached_property
    def stiffness(self) -> sp.csr_matrix:
        """3N x 3N stiffness K (N/m), scipy CSR, dof order (x0, y0, z0, x1, ...)."""
        return sp.csr_matrix(self._core.stiffness_csr())

    def external_forces(self, U: ArrayLike, dp: float) -> NDArray[np.float64]:
        """F_ext = K U - dp a n (N x 3, newtons) for displacements U (N x 3, m), dp (Pa)."""
        U = _validate.nodes_x3("U", U, self.n_nodes)
        dp = _validate.finite_scalar("dp", dp)
        return np.asarray(self._core.external_forces(U, dp))

    def normal_pressure(self, forces: ArrayLike) -> NDArray[np.float64]:
        """p_i = -n_i . F_i / a_i (N,, Pa, inward positive) for nodal forces (N x 3, N)."""
        F = _validate.nodes_x3("forces", forces, self.n_nodes)
        return np.asarray(_core()._normal_pressure(F, self.areas, self.normals))

    def contact_mask(
        self, normal_pressure: ArrayLike, k_const: float = 2000.0, k_linear: float = 2.0
    ) -> NDArray[np.bool_]:
        """Nodes with p_i > max(k_const, k_linear * area-weighted mean p) (N, bool)."""
        p = _validate.nodes_1d("normal_pressure", normal_pressure, self.n_nodes)
        k_const = _validate.finite_scalar("k_const", k_const)
        k_linear = _validate.finite_scalar("k_linear", k_linear)
        return np.asarray(_core()._contact_mask(p, self.areas, k_const, k_linear), dtype=bool)

    def net_force(self, forces: ArrayLike) -> NDArray[np.float64]:
        """Sum of the nodal forces over non-rim nodes (3,, newtons)."""
        F = _validate.nodes_x3("forces", forces, self.n_nodes)
        return np.asarray(_core()._net_force(F, self._interior))

    def __repr__(self) -> str:
        return f"MembraneModel({self.mesh!r}, {self.material!r}, inflation_pa={self.inflation_pa})"


def _readonly(a: NDArray) -> NDArray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a
