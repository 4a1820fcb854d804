"""What the daemon runs on each frame: a Processor (the estimation pipeline or a test fake) and
the contact patches it publishes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from bubble_rt.camera import Camera
from bubble_rt.config import DaemonConfig
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh
from bubble_rt.wrench import PatchFinder as PatchFinder  # the patches the daemon publishes


class Processor(Protocol):
    """What the daemon needs from the estimation side (a real estimator or a test fake)."""

    mesh: Mesh

    def stage1(self, frame: Frame) -> Any:
        """Deformation of one frame (may run concurrently with ``stage2`` of an older one)."""

    def stage2(self, frame: Frame, data: Any) -> Any:
        """An ``Estimate`` (node_forces, normal_pressure, contact, net_force, info, ...)."""

    def set_reference(self, frames: list[Frame]) -> None:
        """Re-capture the reference from untouched frames (tare)."""

    def reconfigure(self, params: dict[str, float]) -> None:
        """Apply Params (k_f, k_u, youngs_modulus, k_const, k_linear) between frames."""

    def cold_start(self) -> None:
        """The next solve starts as the first one did (after a reference or a tare)."""


ProcessorFactory = Callable[[DaemonConfig, Camera, list[Frame]], Processor]


class EstimatorProcessor:
    """The real processor: the estimation ``Pipeline`` the config describes, its two stages
    run by the daemon's two threads."""

    def __init__(
        self,
        config: DaemonConfig,
        camera: Camera,
        frames: list[Frame],
        mesh: Mesh | None = None,
    ) -> None:
        """``mesh``: an already fitted mesh (a replayed recording's), used as it is."""
        from bubble_rt.estimation.pipeline import Pipeline, capture_settings

        settings = capture_settings(config, realtime=True)
        if mesh is not None:
            settings.update(mesh=mesh, fit=False)
        self.pipeline = Pipeline.capture(frames, camera, **settings)
        self.mesh = self.pipeline.mesh

    @property
    def reference(self) -> Any:
        return self.pipeline.reference

    def stage1(self, frame: Frame) -> Any:
        return self.pipeline.deform(frame)

    def stage2(self, frame: Frame, data: Any) -> Any:
        return self.pipeline.solve(frame, data)

    def cold_start(self) -> None:
        """The next solve starts cold (no warm start from the previous frame)."""
        self.pipeline.cold_start()

    def set_reference(self, frames: list[Frame]) -> None:
        """Tare; a reference the plausibility checks refuse raises and the old one stays."""
        self.pipeline.retake_reference(frames)

    def reconfigure(self, params: dict[str, float]) -> None:
        self.pipeline.reconfigure(params)

    def follow_reference(self, reference: Any, offset: Any = None) -> bool:
        """Re-zero: track against ``reference`` (a ``Reference``) and from the nodes moved by
        ``offset`` (N x 3, m) from the next frame on; False when the estimator kind cannot
        (``bubble_rt.daemon.rezero``)."""
        return self.pipeline.follow_reference(reference, offset)
