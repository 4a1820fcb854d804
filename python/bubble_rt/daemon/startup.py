"""The daemon's start-up decisions, from its configuration and camera source: a mesh file
checked before anything starts, a replay's recorded settings, the sensor profile."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from bubble_rt.config import DaemonConfig
from bubble_rt.io import protocol

log = logging.getLogger("bubble_rt.daemon")


def mesh_file_problem(config: DaemonConfig) -> str:
    """Why the configured mesh file cannot be loaded ("" when it can, or is a preset): checked
    at start, so a bad file stops the start instead of every frame."""
    from bubble_rt.mesh import PRESETS, Mesh

    path = config.estimator.mesh
    if path in PRESETS:
        return ""
    try:
        Mesh.load(path)
    except Exception as exc:
        return f"estimator.mesh: cannot load {path!r} as a mesh: {type(exc).__name__}: {exc}"
    return ""


def recorded_settings(config: DaemonConfig, cam: Any) -> tuple[DaemonConfig, Any]:
    """Replay of this project's MCAP (camera.replay_settings = "recorded"): the configuration
    with what the live run used (estimator, flow, solver and reference settings, calibration)
    and its fitted mesh (or None), so the replay reproduces the live forces."""
    text = cam.recorded_settings
    if not text:
        return config, None
    import tomllib

    from bubble_rt.config import ConfigError

    try:
        rec = DaemonConfig.from_dict(tomllib.loads(text))
    except (ConfigError, tomllib.TOMLDecodeError) as exc:
        log.warning("replay: the recorded settings are not usable (%s); using ours", exc)
    else:
        est = replace(rec.estimator, mesh=config.estimator.mesh)
        config = replace(
            config, estimator=est, flow=rec.flow, solver=rec.solver, reference=rec.reference
        )
        log.info("replay: estimating with the recording's settings")
    if cam.recorded_mesh is None:
        return config, None
    from bubble_rt.mesh import Mesh

    m = protocol.decode_mesh(cam.recorded_mesh)
    return config, Mesh(m.vertices, m.triangles.astype(np.int32), m.boundary.astype(np.int32))


def resolve_profile(config: DaemonConfig, layout: str) -> DaemonConfig:
    """The configuration with the sensor profile's ambient pressure written in (unless it
    gives one), so that status, recordings and replays carry the value in use, and "auto"
    resolved by the camera's layout (the plausibility bounds read the profile's bubble)."""
    est = config.estimator
    prof = est.sensor_profile(layout)
    if not est.ambient_pa:
        log.info("sensor profile %s: ambient pressure %.0f Pa", prof.name, prof.ambient_pa)
        est = replace(est, ambient_pa=prof.ambient_pa)
    return replace(config, estimator=replace(est, profile=prof.name))


def takes_mesh(factory: Any) -> bool:
    """Whether a processor factory accepts a ``mesh`` (a replay's recorded mesh)."""
    import inspect

    try:
        return "mesh" in inspect.signature(factory).parameters
    except (TypeError, ValueError):
        return False
