"""Paper-faithful reference implementation (NumPy / SciPy / CVXPY), independent of the C++ core.

This module restates the paper's membrane model and group lasso (and the public implementation's
deformation pipeline) in plain Python so that the fast path can be tested and benchmarked against
it. It shares no code with ``bubble_rt._core``, ``membrane``, ``solver`` or ``estimator``; it takes
plain arrays (a ``Mesh``'s ``vertices``, ``triangles``, ``boundary``) and the shared ``Camera``.

Units: metres, newtons, pascals. Displacements and forces are N x 3 arrays, node-major; the
stiffness matrix uses the degree-of-freedom order ``[x0, y0, z0, x1, y1, z1, ...]``.

Sign convention (as the estimator's, docs/method.md): ``F_ext = K U - dp a n`` is the force the
environment applies on each node; ``p = -n . F_ext / a`` is the inward normal pressure.

Everything here is single-threaded by intent (CVXPY + Clarabel, SciPy); set
``OPENBLAS_NUM_THREADS=1`` when timing it so the comparison with the C++ path is fair.
"""

from __future__ import annotations

from bubble_rt.reference.model import (
    contact_mask,
    external_forces,
    lasso_weights,
    lumped_areas,
    net_force,
    normal_pressure,
    stiffness_matrix,
    vertex_normals,
)
from bubble_rt.reference.pipeline import ReferencePipeline, ReferenceSettings
from bubble_rt.reference.problem import GroupLassoProblem
from bubble_rt.reference.raycast import RayHits, raycast_mesh, render_depth

__all__ = [
    "stiffness_matrix",
    "lumped_areas",
    "vertex_normals",
    "external_forces",
    "normal_pressure",
    "contact_mask",
    "net_force",
    "lasso_weights",
    "GroupLassoProblem",
    "RayHits",
    "raycast_mesh",
    "render_depth",
    "ReferenceSettings",
    "ReferencePipeline",
]
