"""bubble_rt: real-time 3D contact forces and contact patches from a soft-bubble tactile sensor.

Public names are imported lazily so that `import bubble_rt` stays cheap and a tool that needs
only the protocol (a subscriber client) never loads the C++ core.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "Mesh": "mesh",
    "MeshGeometry": "mesh",
    "MeshError": "mesh",
    "Camera": "camera",
    "Frame": "frames",
    "FrameError": "frames",
    "Material": "estimation.membrane",
    "MembraneModel": "estimation.membrane",
    "SolverSettings": "estimation.solver",
    "SolverInfo": "estimation.solver",
    "GroupLassoSolver": "estimation.solver",
    "EstimatorConfig": "estimation.estimator",
    "ForceEstimator": "estimation.estimator",
    "Estimate": "estimation.estimator",
    "make_estimator": "estimation.registry",
    "Pipeline": "estimation.pipeline",
    "SolverResult": "estimation.solver",
    "Reference": "estimation.deformation",
    "DeformationTracker": "estimation.deformation",
    "FlowSettings": "estimation.deformation",
    "fit_mesh": "estimation.fitting",
    "open_recording": "io.recordings",
    "FrictionlessEstimator": "estimation.baseline",
    "FrictionlessSettings": "estimation.baseline",
    "ReferencePipeline": "reference",
    "GroupLassoProblem": "reference",
    "DaemonConfig": "config",
    "Subscriber": "io.client",
    "Controller": "io.client",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"bubble_rt.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'bubble_rt' has no attribute {name!r}")
