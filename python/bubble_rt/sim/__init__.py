"""Scene simulator: nonlinear membrane physics, indenters, rendering and ground truth.

Physics (``bubble_rt.sim.physics``) and indenters (``bubble_rt.sim.indenters``) are imported
lazily so that importing the package stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "MembraneMaterial": "physics",
    "GasSettings": "physics",
    "ContactSettings": "physics",
    "NewtonSettings": "physics",
    "SimState": "physics",
    "MembraneSim": "physics",
    "SimConvergenceError": "physics",
    "default_rest_mesh": "physics",
    "Sphere": "indenters",
    "Capsule": "indenters",
    "Box": "indenters",
    "Union": "indenters",
    "Indenter": "indenters",
    "Simulator": "simulator",
    "PhysicsRun": "simulator",
    "load_scene": "scene",
    "Scene": "scene",
    "SceneError": "scene",
    "GroundTruth": "truth",
    "dataset_scenes": "dataset",
    "DatasetSettings": "dataset",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"bubble_rt.sim.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'bubble_rt.sim' has no attribute {name!r}")
