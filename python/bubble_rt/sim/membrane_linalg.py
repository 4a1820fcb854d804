"""Linear algebra of the simulated membrane's Newton steps (``bubble_rt.sim.physics``).

The Newton system is ``(H + c u u^T) d = -g`` on the M x 3 node displacements: H the sparse
membrane + contact Hessian held (assembled and factorised) by ``_core._SimMembrane``, and the
dense rank-one gas term c u u^T (u = dV/dx, c = d2E/dV2) handled by Sherman-Morrison.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.sim.membrane_state import Array


def pcg(
    sys: Any,
    g: Array,
    dV: Array,
    d2E: float,
    rtol: float,
    free: NDArray[np.bool_],
    max_iterations: int,
    stats: dict[str, int],
    coupled: Callable[[Array], Array] | None = None,
) -> Array | None:
    """Solve (H + d2E u u^T) d = -g by CG preconditioned with the last factorisation
    (Sherman-Morrison for the rank-one part); H is the assembled matrix plus the surface
    samples' node coupling (``coupled(v)``: its product with v, M x 3). ``sys`` is the
    ``_core._SimMembrane`` holding the assembled matrix and its factorisation; ``free`` (M,)
    the nodes off the rim; ``stats`` counts "solves" and "cg_iterations". None when it does
    not converge in ``max_iterations`` or meets a direction of non-positive curvature."""
    u = dV.copy()
    u[~free] = 0.0
    c = d2E
    w = sys.solve(u) if c else None
    stats["solves"] += 1 if c else 0
    den = 1.0 + c * float(np.sum(u * w)) if w is not None else 1.0

    def op(v: Array) -> Array:
        out = sys.multiply(v)
        if coupled is not None:
            out += coupled(v)
        if c:
            out += (c * float(np.sum(u * v))) * u
        return out

    def prec(r: Array) -> Array:
        z = sys.solve(r)
        stats["solves"] += 1
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
    n_max = max_iterations
    for k in range(1, n_max + 1):
        Ap = op(p)
        pAp = float(np.sum(p * Ap))
        if not pAp > 0:
            return None
        a = rz / pAp
        xk += a * p
        r -= a * Ap
        if float(np.sqrt(np.sum(r * r))) <= rtol * nb:
            stats["cg_iterations"] += k
            return xk
        z = prec(r)
        rz_new = float(np.sum(r * z))
        p = z + (rz_new / rz) * p
        rz = rz_new
    stats["cg_iterations"] += n_max
    return None


def sherman_morrison_direction(
    sys: Any, g: Array, dV: Array, d2E: float, free: NDArray[np.bool_]
) -> Array:
    """Newton direction (M x 3) with (A + c u u^T) d = -g via Sherman-Morrison: A factorised
    in ``sys``, u = dV (M x 3) with rim rows zeroed, c = d2E."""
    y1 = sys.solve(-g)
    if d2E == 0.0:
        return y1
    u = dV.copy()
    u[~free] = 0.0
    y2 = sys.solve(u)
    return y1 - y2 * (d2E * float(np.sum(u * y1)) / (1.0 + d2E * float(np.sum(u * y2))))
