"""Linear plane-stress membrane model (method.md section 2), backed by the C++ core.

Units: metres, pascals, newtons. Sign convention: ``F_ext(U, dp) = K U - dp * a_i * n_i`` is
the force the object applies on each node; normal pressure ``p_i = -n_i . F_i / a_i`` is
positive inward.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

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
        if not -1.0 < nu <= 0.5:
            raise ValueError(f"nu must be in (-1, 0.5], got {nu}")


def _core():  # noqa: ANN202 - private extension module
    from bubble_rt import _core as core

    return core


class MembraneModel:
    """Constant-strain-triangle membrane of a mesh, built once per mesh and material.

    Attributes:
        mesh: the reference (inflated, untouched) mesh.
        material: the Material used.
        areas: (N,) lumped areas a_i (m^2), a third of each incident triangle.
        normals: (N, 3) area-weighted outward unit normals.
        area_normals: (N, 3) a_i * n_i (m^2), the force per pascal of pressure.
    """

    def __init__(self, mesh: Mesh, material: Material | None = None) -> None:
        self.mesh = mesh
        self.material = material or Material()
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

    @property
    def n_nodes(self) -> int:
        return int(self.areas.shape[0])

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
        return f"MembraneModel({self.mesh!r}, {self.material!r})"


def _readonly(a: NDArray) -> NDArray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a
