"""The on-disk cache of derived arrays (simulated physics, generated meshes).

Location: ``$BUBBLE_RT_CACHE`` if set, else ``~/.cache/bubble_rt``. Entries are ``.npz`` files
named by a key that hashes everything the arrays depend on; they are written atomically, so
concurrent runs are safe, and an unreadable entry reads as absent (it is then recomputed).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def cache_dir() -> Path:
    """The cache directory (created on demand)."""
    env = os.environ.get("BUBBLE_RT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "bubble_rt"


def source_key(*parts: object, files: tuple[Path, ...] = ()) -> str:
    """A hex key hashing ``parts`` (their ``repr``) and the bytes of ``files`` (the code that
    computes the entry, so an edit to it invalidates the entry)."""
    h = hashlib.sha256()
    for p in parts:
        h.update(repr(p).encode())
        h.update(b"\0")
    for f in files:
        h.update(Path(f).read_bytes())
    return h.hexdigest()[:24]


def load(path: Path) -> dict[str, NDArray] | None:
    """The arrays stored at ``path``, or None when absent or unreadable."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, EOFError):
        return None


def store(path: Path, arrays: dict[str, NDArray]) -> Path:
    """Write ``arrays`` to ``path`` atomically (a temporary file renamed into place)."""
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
