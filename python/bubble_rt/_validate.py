"""Input checks shared by the core facades (private).

Every check raises ValueError naming the argument before anything reaches C++, so a bad call
writes nothing and leaves solver state intact.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray


def nodes_x3(name: str, value: ArrayLike, n: int) -> NDArray[np.float64]:
    """``value`` as a C-contiguous float64 N x 3 array (no copy when it already is one)."""
    try:
        a = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} must be an array of shape ({n}, 3): {exc}") from exc
    if a.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be numeric, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has NaN or inf at node {int(np.flatnonzero(bad)[0])}")
    return a


def nodes_1d(name: str, value: ArrayLike, n: int) -> NDArray[np.float64]:
    """``value`` as a finite C-contiguous float64 vector of length n."""
    a = np.asarray(value)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has NaN or inf at node {int(np.flatnonzero(~np.isfinite(a))[0])}")
    return a


def finite_scalar(name: str, value: object) -> float:
    """``value`` as a finite float (pascals, newtons, ...)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {value!r}") from exc
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def positive(name: str, value: object) -> float:
    v = finite_scalar(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be positive, got {v}")
    return v
