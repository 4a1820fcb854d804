"""Sensor frames: what one camera exposure plus the matching pressure reading carry.

Units: RGB H x W x 3 uint8 (RGB order); depth H x W float32 metres of camera z, 0 where invalid;
pressure in pascals (absolute or gauge, as long as the reference uses the same); times in
seconds (any monotonic clock shared by the sources).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

HPA = 100.0  # pascals per hectopascal


class FrameError(ValueError):
    """A frame is malformed; the message names the field at fault."""


@dataclass
class Frame:
    """One synchronised sensor sample.

    Attributes:
        rgb: H x W x 3 uint8 colour image (RGB order), or None (oracle frames from the simulator).
        depth: H x W float32 depth (metres, camera z), 0 where invalid, or None.
        pressure_pa: air pressure, pascals.
        t: capture time of the camera frame, seconds.
        t_pressure: time of the pressure reading, seconds (None: same as ``t``).
        wrench: ground-truth [fx, fy, fz, tx, ty, tz] from a force/torque sensor (N, N m), or None.
        truth: simulator ground truth (``bubble_rt.sim.GroundTruth``), or None.
        index: sequence number within its source.
        meta: free-form extras (e.g. degraded reasons, source name).
    """

    rgb: NDArray[np.uint8] | None
    depth: NDArray[np.float32] | None
    pressure_pa: float
    t: float = 0.0
    t_pressure: float | None = None
    wrench: NDArray[np.float64] | None = None
    truth: Any = None
    index: int = 0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int] | None:
        """(H, W) of the images, or None when the frame has none."""
        img = self.rgb if self.rgb is not None else self.depth
        return None if img is None else (int(img.shape[0]), int(img.shape[1]))
