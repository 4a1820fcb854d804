"""The wire format between the simulated camera's renderer process and the daemon
(:mod:`bubble_rt.daemon.sim_producer`), also the layout of the rendered-frame caches
(:mod:`bubble_rt.daemon.sim_cache`).

A message is a JSON header line ``{"kind": ..., "arrays": [[name, dtype, shape], ...], ...}``
followed by the raw bytes of those arrays. A frame travels without its truth (the parent
rebuilds it from the simulator): its scalars in the header, its images as arrays.
"""

from __future__ import annotations

import json
from typing import IO, Any

import numpy as np

from bubble_rt.frames import Frame

#: A frame's array fields (None ones are not sent) and scalar fields.
FRAME_ARRAYS = ("rgb", "depth", "wrench")
FRAME_SCALARS = ("pressure_pa", "t", "t_pressure", "index")


def write_message(
    out: IO[bytes], kind: str, arrays: dict[str, Any] | None = None, **fields: Any
) -> None:
    """One message: a JSON header line, then the raw bytes of ``arrays`` (None ones omitted)."""
    present = {k: np.ascontiguousarray(v) for k, v in (arrays or {}).items() if v is not None}
    header = dict(fields, kind=kind)
    header["arrays"] = [[k, a.dtype.str, list(a.shape)] for k, a in present.items()]
    out.write(json.dumps(header).encode() + b"\n")
    for a in present.values():
        out.write(a.reshape(-1).view(np.uint8).data)
    out.flush()


def read_message(inp: IO[bytes]) -> tuple[dict[str, Any], dict[str, np.ndarray]] | None:
    """The next message (header, arrays), or None at the end of the stream."""
    line = inp.readline()
    if not line:
        return None
    header = json.loads(line)
    arrays = {}
    for name, dtype, shape in header.pop("arrays"):
        a = np.empty(shape, dtype=np.dtype(dtype))
        view = a.reshape(-1).view(np.uint8).data
        got = 0
        while got < a.nbytes:  # readinto may return short counts on a pipe
            n = inp.readinto(view[got:])  # type: ignore[attr-defined]
            if not n:
                return None
            got += n
        arrays[name] = a
    return header, arrays


def frame_message(frame: Frame) -> tuple[dict[str, Any], dict[str, Any]]:
    """(fields, arrays) carrying ``frame`` without its truth (rebuilt by the parent)."""
    fields = {k: getattr(frame, k) for k in FRAME_SCALARS}
    fields["meta"] = {
        k: v for k, v in frame.meta.items() if isinstance(v, str | int | float | bool)
    }
    return fields, {k: getattr(frame, k) for k in FRAME_ARRAYS}


def message_frame(header: dict[str, Any], arrays: dict[str, np.ndarray], truth: Any) -> Frame:
    return Frame(
        rgb=arrays.get("rgb"),
        depth=arrays.get("depth"),
        wrench=arrays.get("wrench"),
        truth=truth,
        meta=dict(header["meta"]),
        **{k: header[k] for k in FRAME_SCALARS},
    )
