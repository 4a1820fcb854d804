"""What the daemon runs on each frame: a Processor (the estimation pipeline or a test fake) and
the contact patches it publishes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.config import DaemonConfig
from bubble_rt.frames import Frame
from bubble_rt.io import protocol
from bubble_rt.mesh import Mesh


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
        from bubble_rt.estimation.deformation import Reference

        self.pipeline.set_reference(Reference.capture(frames))

    def reconfigure(self, params: dict[str, float]) -> None:
        self.pipeline.reconfigure(params)

    def follow_reference(self, reference: Any, offset: Any = None) -> bool:
        """Re-zero: track against ``reference`` (a ``Reference``) and from the nodes moved by
        ``offset`` (N x 3, m) from the next frame on; False when the estimator kind cannot
        (``bubble_rt.daemon.rezero``)."""
        return self.pipeline.follow_reference(reference, offset)


class PatchFinder:
    """Contact patches: connected components of the contact mask over mesh edges."""

    def __init__(self, mesh: Mesh) -> None:
        self.adjacency = mesh.adjacency()
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.areas = mesh.lumped_areas()

    def patches(
        self, contact: NDArray, node_forces: NDArray, displacements: NDArray | None = None
    ) -> list[protocol.Patch]:
        from scipy.sparse.csgraph import connected_components

        idx = np.flatnonzero(np.asarray(contact, dtype=bool))
        if idx.size == 0:
            return []
        sub = self.adjacency[idx][:, idx]
        n_comp, labels = connected_components(sub, directed=False)
        pos = self.vertices if displacements is None else self.vertices + displacements
        out = []
        for c in range(n_comp):
            nodes = idx[labels == c]
            a = self.areas[nodes]
            area = float(a.sum())
            w = a / area if area > 0 else np.full(len(nodes), 1.0 / len(nodes))
            out.append(
                protocol.Patch(
                    centroid=w @ pos[nodes],
                    area=area,
                    force=np.asarray(node_forces, dtype=np.float64)[nodes].sum(axis=0),
                    nodes=nodes.astype(np.int64),
                )
            )
        out.sort(key=lambda p: -float(np.linalg.norm(p.force)))
        return out
