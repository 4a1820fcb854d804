"""Daemon helpers for what can go wrong: recordings (start, stop, failure), solver outcomes,
reference pressure, fault counts in the status.

Kept out of :mod:`bubble_rt.daemon.service` so the daemon only calls small functions here.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from bubble_rt.frames import Frame

#: Solver outcomes published as normal frames; any other status marks the frame degraded.
ACCEPTABLE_SOLVER_STATUS = ("solved", "max_iter_reached", "time_limit_reached")
#: How long a skipped bad frame keeps the status degraded, seconds.
BAD_FRAME_HOLD_S = 2.0


# ------------------------------------------------------------------------------ recording
def recording_path(requested: str, directory: str) -> Path:
    """The file ``record_start`` writes: ``requested``, or a timestamped file in the
    configured ``directory`` (created if missing: it is the daemon's own configuration;
    folders of a requested path are never created)."""
    if requested:
        return Path(requested)
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ValueError(
            f"recording.directory {directory!r} is (or is under) a file, not a folder"
        ) from None
    except OSError as exc:
        raise ValueError(
            f"recording.directory {directory!r}: cannot create: {exc.strerror or exc}"
        ) from None
    return d / time.strftime("bubble_rt-%Y%m%d-%H%M%S.mcap", time.gmtime())


def start_recorder(
    path: str | Path,
    config: Any,
    camera: Any,
    mesh_msg: Any,
    reference: list[Frame],
    overwrite: bool = False,
) -> Any:
    """A running :class:`~bubble_rt.io.mcap_writer.Recorder` (raises RecordingPathError with the
    reason: existing file without ``overwrite``, not a regular file, no such folder).

    Only a non-blocking open happens here; all writing is on the recorder's own thread, so
    this is safe on the control thread.
    """
    from bubble_rt.io.mcap_writer import Recorder

    rc = config.recording
    rec = Recorder(
        path,
        camera,
        mesh_msg,
        inputs=rc.inputs,
        chunk_size=rc.chunk_size,
        compression=rc.compression,
        color=rc.color,
        jpeg_quality=rc.jpeg_quality,
        queue_size=rc.queue,
        overwrite=overwrite,
    )
    if reference:
        rec.write_reference(reference)
    write_settings(rec, config)
    return rec


def write_settings(rec: Any, config: Any) -> None:
    """Record the configuration the estimate depends on (replay uses it)."""
    from bubble_rt.io.mcap import TOPIC_SETTINGS
    from bubble_rt.io.protocol import pb

    rec.write_message(TOPIC_SETTINGS, pb.ControlReply(ok=True, config_toml=config.to_toml()))


def stop_recorder(rec: Any, timeout: float = 1.5) -> tuple[bool, str]:
    """Finalise a recording, waiting at most ``timeout`` s: (ok, path or error text)."""
    done = rec.close(timeout=timeout)
    where = str(Path(rec.path).resolve()) if str(rec.path) else str(rec.path)
    if rec.failed:
        return False, f"record_stop: {rec.failed}; the file is incomplete"
    if not done:
        return False, (
            f"record_stop: {where} is still being written after {timeout:g} s (slow disk?); "
            "it is finalised in the background"
        )
    return True, where


def recording_state(rec: Any) -> tuple[bool, str, int]:
    """(recording, recording_error, dropped) for the status."""
    if rec is None:
        return False, "", 0
    return not rec.failed, rec.failed, int(rec.dropped)


# ------------------------------------------------------------------------------ solver
def solver_problem(info: Any) -> str | None:
    """A degraded reason when the solver's status is not solved or an accepted limit."""
    status = getattr(info, "status", None)
    if status is None or status in ACCEPTABLE_SOLVER_STATUS:
        return None
    return f"solver status {status}: forces not valid"


def forces_problem(node_forces: Any, net_force: Any) -> str | None:
    """A degraded reason when the estimate has non-finite values."""
    import numpy as np

    if not (np.isfinite(node_forces).all() and np.isfinite(net_force).all()):
        return "non-finite forces"
    return None


# ------------------------------------------------------------------------------ pressure
def reference_with_pressure(
    frames: list[Frame], at: Callable[[float], tuple[float, float, float] | None]
) -> list[Frame] | None:
    """Reference frames given by the camera source (simulator, recording) with the pressure
    of the pressure source in use (``PressureBuffer.at``), so dp is measured against the
    sensor that reads the frames; None while that source has no reading yet."""
    out = []
    for f in frames:
        got = at(f.t)
        if got is None:
            return None
        p, t_sample, _ = got
        meta = dict(f.meta)
        meta.setdefault("source_pressure_pa", f.pressure_pa)
        out.append(replace(f, pressure_pa=p, t_pressure=t_sample, meta=meta))
    return out


# ------------------------------------------------------------------------------ status
def add_source_stats(msg: Any, stats: Any, now: float) -> None:
    """Append one source's counters, per fault kind included, to a Status message."""
    s = msg.sources.add(
        name=stats.name,
        received=stats.received,
        errors=stats.n_errors,
        last_error=stats.last_error,
        age_s=stats.age(now),
    )
    for kind, n in stats.errors.items():
        s.error_counts[kind] = int(n)


def add_daemon_stats(msg: Any, errors: Mapping[str, int], last_error: str) -> None:
    s = msg.sources.add(name="daemon", errors=sum(errors.values()), last_error=last_error)
    for kind, n in errors.items():
        s.error_counts[kind] = int(n)


def bad_frame_reason(cam: Any, now: float) -> str:
    """Degraded reason while a camera source recently skipped a bad frame ("" if none)."""
    bad = getattr(cam, "bad_frames", None)
    if not bad:
        return ""
    st = cam.stats
    if now - st.last_error_time > BAD_FRAME_HOLD_S or not st.last_error.startswith("skipped"):
        return ""
    n = st.errors.get("bad_frame", 0) + st.errors.get("bad_reading", 0)
    return f"{st.last_error} ({n} skipped so far)"
