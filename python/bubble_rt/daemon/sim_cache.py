"""The disk caches of the simulated camera's rendered frames: the reference frames (read by
:mod:`bubble_rt.daemon.sim_producer`) and one whole rendered pass of a scene (read by
:mod:`bubble_rt.daemon.sim_camera`). Keyed by the scene, the simulator's code and the
versions, so a cached frame is byte-identical to a rendered one.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from bubble_rt.daemon.sim_wire import FRAME_ARRAYS, frame_message
from bubble_rt.frames import Frame


def _render_key(sim: Any, what: str, n: int) -> str | None:
    """A key for frames ``sim`` rendered, or None (a simulator without a scene description,
    e.g. a test fake). It hashes the scene (seed, sensor, effects, ...), ``what`` and ``n``,
    the simulator's code (every ``bubble_rt/sim`` module and the C++ core the renderer calls)
    and the versions: rendering them again gives the same bytes."""
    import dataclasses

    import bubble_rt
    from bubble_rt import _diskcache

    scene = getattr(sim, "scene", None)
    if not dataclasses.is_dataclass(scene) or isinstance(scene, type):
        return None
    pkg = Path(bubble_rt.__file__).parent
    code = tuple(sorted((pkg / "sim").glob("*.py"))) + tuple(sorted(pkg.glob("_core*.so")))
    described = json.dumps(dataclasses.asdict(scene), sort_keys=True, default=str)
    return _diskcache.source_key(
        what, described, n, bubble_rt.__version__, np.__version__, files=code
    )


def reference_cache_path(sim: Any, n: int) -> Path | None:
    """Where ``n`` rendered reference frames of ``sim``'s scene are kept (about 2 MB a frame),
    or None (see ``_render_key``)."""
    from bubble_rt import _diskcache

    key = _render_key(sim, "sim-reference", n)
    return None if key is None else _diskcache.cache_dir() / f"simref-{key}.npz"


def pass_cache_path(sim: Any) -> Path | None:
    """The folder where one rendered pass of ``sim``'s scene is kept (``rgb.npy``,
    ``depth.npy``, ``fields.json``; about 2 MB a frame, 260 MB for the 120-frame demo), or
    None (see ``_render_key``)."""
    from bubble_rt import _diskcache

    key = _render_key(sim, "sim-pass", int(sim.scene.frames) if hasattr(sim, "scene") else 0)
    return None if key is None else _diskcache.cache_dir() / f"simpass-{key}"


def load_pass(
    path: Path, n_frames: int
) -> list[tuple[dict[str, Any], dict[str, np.ndarray]]] | None:
    """A cached pass as (fields, arrays) per frame, the images memory-mapped from the files
    (read as the frames are used, copy-on-write), or None when absent, unreadable or not the
    scene's whole pass of ``n_frames`` frames."""
    try:
        fields = json.loads((path / "fields.json").read_text())
        rgb = np.load(path / "rgb.npy", mmap_mode="c")
        depth = np.load(path / "depth.npy", mmap_mode="c")
        if not (len(rgb) == len(depth) == len(fields) == n_frames):
            return None
        return [(f, {"rgb": rgb[k], "depth": depth[k]}) for k, f in enumerate(fields)]
    except (OSError, ValueError, KeyError):
        return None


def store_pass(path: Path, frames: list[Frame]) -> None:
    """Keep one rendered pass (frames with rgb and depth) for the next runs; written into a
    temporary folder renamed into place, so a reader never sees half of it."""
    import shutil
    import tempfile

    if not frames or any(f.rgb is None or f.depth is None for f in frames) or path.exists():
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, suffix=".tmp"))
    try:
        for name in ("rgb", "depth"):
            first = getattr(frames[0], name)
            out = np.lib.format.open_memmap(
                tmp / f"{name}.npy",
                mode="w+",
                dtype=first.dtype,
                shape=(len(frames),) + first.shape,
            )
            for k, f in enumerate(frames):
                out[k] = getattr(f, name)
            out.flush()
            del out
        (tmp / "fields.json").write_text(json.dumps([frame_message(f)[0] for f in frames]))
        os.replace(tmp, path)
    except OSError:
        pass  # not cached (disk full, read-only, or another run stored it first)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def load_reference(path: Path) -> list[tuple[dict[str, Any], dict[str, np.ndarray]]] | None:
    """The cached reference frames as (fields, arrays) messages, or None."""
    from bubble_rt import _diskcache

    got = _diskcache.load(path)
    if got is None:
        return None
    try:
        fields = json.loads(bytes(got["fields"]).decode())
        out = []
        for k, f in enumerate(fields):
            arrays = {a: got[a][k] for a in FRAME_ARRAYS if a in got}
            out.append((f, arrays))
        return out
    except (KeyError, ValueError, IndexError):
        return None


def store_reference(path: Path, frames: list[Frame]) -> None:
    """Keep rendered reference frames (all with the same array fields) for the next start."""
    from bubble_rt import _diskcache

    msgs = [frame_message(f) for f in frames]
    arrays = {
        a: np.stack([m[1][a] for m in msgs])
        for a in FRAME_ARRAYS
        if all(m[1][a] is not None for m in msgs)
    }
    arrays["fields"] = np.frombuffer(json.dumps([m[0] for m in msgs]).encode(), dtype=np.uint8)
    try:
        _diskcache.store(path, arrays)
    except OSError:
        pass  # not cached: the next start renders them again
