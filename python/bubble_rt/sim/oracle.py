"""The oracle tracker: node displacements from the simulator's ground truth, no images.

Flow method "oracle" (``FlowSettings(method="oracle")``): for every mesh node ``U = truth
.displace(x_ref) - x_ref`` on frames the simulator made (``Frame.truth``), then the same
outlier flags, rim clamp and harmonic fill as the image tracker. Importing this module
registers it with the estimation path's tracker registry (``make_tracker``); the simulator
imports it, so any process that simulates frames can track them this way.
"""

from __future__ import annotations

import time

import numpy as np

from bubble_rt.camera import Camera
from bubble_rt.estimation.deformation import (
    FLAG_NON_FINITE,
    Deformation,
    FlowSettings,
    NodeTracker,
    Reference,
    register_tracker,
)
from bubble_rt.estimation.names import ORACLE_FLOW_METHOD
from bubble_rt.frames import Frame, FrameError
from bubble_rt.mesh import Mesh


class OracleTracker(NodeTracker):
    """Ground-truth displacements of the mesh nodes (same arguments as DeformationTracker;
    the camera is not used)."""

    def __init__(
        self,
        mesh: Mesh,
        camera: Camera | None,
        reference: Reference,
        settings: FlowSettings | None = None,
    ) -> None:
        super().__init__(mesh, reference, settings or FlowSettings(method=ORACLE_FLOW_METHOD))
        self.camera = camera

    def track(self, frame: Frame) -> Deformation:
        """Displacements of the mesh nodes in ``frame`` (a simulator frame) against the reference."""
        n = self.mesh.n_nodes
        dp = self.dp(frame)
        t0 = time.perf_counter()
        if frame.truth is None:
            raise FrameError("truth is missing: method 'oracle' needs simulator frames")
        x_cur = np.asarray(frame.truth.displace(self.x_ref), dtype=np.float64)
        if x_cur.shape != (n, 3):
            raise FrameError(f"truth.displace returned shape {x_cur.shape}, want ({n}, 3)")
        flags = np.zeros(n, np.uint8)
        flags[~np.isfinite(x_cur).all(axis=1)] |= FLAG_NON_FINITE
        timings = {"flow": 0.0, "lift": (time.perf_counter() - t0) * 1e3}
        return self.finish(x_cur - self.x_ref, flags, dp, timings, np.zeros((n, 2)))


register_tracker(ORACLE_FLOW_METHOD, OracleTracker)
