"""On-disk cache of physics results (the expensive part of a simulation).

Entries are keyed by a hash of everything the physics depends on in the scene plus the package
version (``Scene.physics_key``). Location and atomic writes: :mod:`bubble_rt._diskcache`
(``$BUBBLE_RT_CACHE`` if set, else ``~/.cache/bubble_rt``), so concurrent runs are safe.
"""

from __future__ import annotations

from pathlib import Path

from numpy.typing import NDArray

from bubble_rt import _diskcache
from bubble_rt._diskcache import cache_dir

__all__ = ["cache_dir", "cache_path", "load", "store"]


def cache_path(key: str) -> Path:
    return cache_dir() / f"physics-{key}.npz"


def load(key: str) -> dict[str, NDArray] | None:
    """The cached arrays for ``key``, or None when absent or unreadable."""
    return _diskcache.load(cache_path(key))


def store(key: str, arrays: dict[str, NDArray]) -> Path:
    """Write arrays for ``key`` atomically; returns the file path."""
    return _diskcache.store(cache_path(key), arrays)
