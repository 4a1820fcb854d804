"""A kinematic stand-in for the membrane physics, for simulator tests that must not depend on
(or wait for) the real solver: inflation is the analytic dome, contact pushes nodes out of a
sphere along -z, and forces are a stiff spring on the push."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from bubble_rt.mesh import Mesh, MeshGeometry


@dataclass
class FakeState:
    vertices: np.ndarray
    triangles: np.ndarray
    pressure_pa: float
    volume_m3: float
    contact_forces: np.ndarray
    contact: np.ndarray
    converged: bool = True
    iterations: int = 1


class FakeSphere:
    def __init__(self, radius: float = 0.012) -> None:
        self.radius = radius

    def distance(self, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - pose[:3, 3], axis=1) - self.radius


class FakeSim:
    def __init__(self, rest: Mesh, pressure: float) -> None:
        self.rest = rest
        self.p = pressure
        g = MeshGeometry()
        v = rest.vertices.copy()
        v[:, 2] = g.height(v[:, 0], v[:, 1])
        self.ref = v

    def inflate(self) -> FakeState:
        n = len(self.ref)
        return FakeState(
            self.ref, self.rest.triangles, self.p, 1e-4, np.zeros((n, 3)), np.zeros(n, bool)
        )

    def solve(self, indenter: FakeSphere, pose: np.ndarray) -> FakeState:
        v = self.ref.copy()
        c = pose[:3, 3]
        d = indenter.distance(v, pose)
        inside = d < 0
        inside[self.rest.boundary] = False
        # Push penetrating nodes straight down onto the sphere's lower surface.
        dx = v[inside, :2] - c[:2]
        h = np.sqrt(np.maximum(indenter.radius**2 - (dx**2).sum(axis=1), 0.0))
        v[inside, 2] = c[2] - h
        f = np.zeros_like(v)
        f[inside, 2] = -2000.0 * (self.ref[inside, 2] - v[inside, 2])
        return FakeState(v, self.rest.triangles, self.p + 10.0 * inside.sum(), 1e-4, f, inside)


class FakePhysics:
    """Implements bubble_rt.sim.simulator.PhysicsBackend."""

    def __init__(self) -> None:
        self.calls = 0

    def rest_mesh(self, sim_nodes: int, rest_dome_height_m: float) -> Mesh:
        return Mesh.generate(sim_nodes)

    def create(self, scene: Any, rest_mesh: Mesh) -> FakeSim:
        self.calls += 1
        return FakeSim(rest_mesh, scene.physics.atmospheric_pa + scene.physics.gauge_pressure_pa)

    def indenter(self, spec: Any) -> FakeSphere:
        return FakeSphere()

    def distance(self, indenter: FakeSphere, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        return indenter.distance(points, pose)


def small_scene(effects: str = "[]", frames: int = 6, nodes: int = 300, seed: int = 0) -> Any:
    """A short pressing scene (TOML text parsed) for fast tests."""
    from bubble_rt.sim.scene import parse_scene

    text = f"""
name = "small"
seed = {seed}
frames = {frames}
effects = {effects}

[sensor]
sim_nodes = {nodes}

[trajectory]
keyframes = [
  {{ t = 0.0, at = [0.0, 0.0], depth = -0.002 }},
  {{ t = {(frames - 1) / 30.0}, at = [0.005, 0.0], depth = 0.006 }},
]
"""
    return parse_scene(text)
