"""The daemon's sources from its configuration: the camera (``[camera] source``: sim, replay
or realsense) and the pressure (``[pressure] source``: camera, constant or serial)."""

from __future__ import annotations

from typing import Any

from bubble_rt.daemon.devices import RealSenseCamera, SerialPressure
from bubble_rt.daemon.sim_camera import SimCamera
from bubble_rt.daemon.sources import (
    CameraSource,
    ConstantPressure,
    PressureBuffer,
    ReplayCamera,
    SourceError,
    ThreadedSource,
)


def make_camera_source(cfg: Any) -> CameraSource:
    """Camera source from a :class:`~bubble_rt.config.CameraConfig`."""
    from bubble_rt.config import split_source

    kind, arg = split_source(cfg.source)
    if kind == "sim":
        return SimCamera(
            arg or "demo", loop=cfg.loop, lossless=cfg.pace == "fast", prerender=cfg.sim_prerender
        )
    if kind == "replay":
        return ReplayCamera(
            arg,
            realtime=cfg.pace == "realtime",
            loop=cfg.loop,
            recorded=cfg.replay_settings == "recorded",
        )
    if kind == "realsense":
        return RealSenseCamera(arg, cfg.width, cfg.height, cfg.fps)
    raise SourceError(f"unknown camera source {cfg.source!r}")


def make_pressure_source(
    cfg: Any, camera: CameraSource
) -> tuple[PressureBuffer, ThreadedSource | None]:
    """(buffer the daemon interpolates, thread feeding it or None) from a PressureConfig."""
    from bubble_rt.config import split_source

    kind, arg = split_source(cfg.source)
    if kind == "constant":
        return ConstantPressure(float(arg)), None
    buf = PressureBuffer(cfg.buffer)
    if kind == "camera":
        camera.pressure_out = buf
        return buf, None
    if kind == "serial":
        return buf, SerialPressure(
            arg, buf, cfg.baud, cfg.default_unit, cfg.min_pa, cfg.max_pa, cfg.reconnect_s
        )
    raise SourceError(f"unknown pressure source {cfg.source!r}")
