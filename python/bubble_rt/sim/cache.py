"""On-disk cache of physics results (the expensive part of a simulation).

Entries are keyed by a hash of everything the physics depends on in the scene plus the package
version (``Scene.physics_key``). Location: ``$BUBBLE_RT_CACHE`` if set, else
``~/.cache/bubble_rt``. Files are written atomically, so concurrent runs are safe.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def cache_dir() -> Path:
    """The cache directory (created on demand)."""
    env = os.environ.get("BUBBLE_RT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "bubble_rt"


def cache_path(key: str) -> Path:
    return cache_dir() / f"physics-{key}.npz"


def load(key: str) -> dict[str, NDArray] | None:
    """The cached arrays for ``key``, or None when absent or unreadable."""
    path = cache_path(key)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError):
        return None


def store(key: str, arrays: dict[str, NDArray]) -> Path:
    """Write arrays for ``key`` atomically; returns the file path."""
    path = cache_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)  # type: ignore[arg-type]
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
