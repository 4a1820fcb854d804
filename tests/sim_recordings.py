"""Simulated recordings on disk in the real layouts (Punyo .npy, the project's MCAP), with a
force/torque wrench the test knows: ``w = R_ft^T f_true + bias`` (force) in the F/T sensor's
frame, where ``R_ft`` maps F/T-frame vectors into the mesh frame. The files carry no
simulation truth (like a real sensor's)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from bubble_rt.camera import Camera
from bubble_rt.eval.tasks import SimTrajectory
from bubble_rt.frames import Frame

HPA = 100.0


def rotation(axis: tuple[float, float, float], deg: float) -> np.ndarray:
    """Rodrigues: rotation by ``deg`` degrees about ``axis``."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * (K @ K)


def with_wrench(
    frames: list[Frame], R_ft: np.ndarray, bias: np.ndarray, rng: np.random.Generator | None = None
) -> list[Frame]:
    """Frames with ``wrench = [R_ft^T f_true + bias[:3], bias[3:] (+ a torque of the force)]``
    and no truth (the truth's net force is zero for reference frames without one)."""
    out = []
    for f in frames:
        t = f.truth
        force = np.zeros(3) if t is None else np.asarray(t.net_force, dtype=float)
        w_force = R_ft.T @ force + bias[:3]
        w_torque = bias[3:] + np.cross([0.0, 0.0, 0.05], R_ft.T @ force)
        w = np.concatenate([w_force, w_torque])
        if rng is not None:
            w = w + rng.normal(0.0, 1e-3, 6)
        out.append(replace(f, wrench=w, truth=None))
    return out


def saturated_to_invalid(frames: list[Frame], max_depth_m: float = 0.5) -> list[Frame]:
    """Depth beyond ``max_depth_m`` (the simulated camera's saturated 6.55 m) as invalid (0),
    as the Punyo reader does, so every layout and the frames in memory hold the same data."""
    out = []
    for f in frames:
        if f.depth is None:
            out.append(f)
            continue
        d = np.where(f.depth < max_depth_m, f.depth, np.float32(0)).astype(np.float32)
        out.append(replace(f, depth=d))
    return out


def deproject(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Organised (H*W x 3) camera-frame point cloud of a depth image (zeros where invalid)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    z = depth.astype(np.float64)
    x = (u - camera.cx) / camera.fx * z
    y = (v - camera.cy) / camera.fy * z
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    pts[z.ravel() <= 0] = 0.0
    return pts.astype(np.float32)


def write_punyo(path: Path, frames: list[Frame], camera: Camera) -> Path:
    """The Punyo layout (expand/{rgb,pc,pressure}_<i>.npy, data.json with the wrench)."""
    exp = path / "expand"
    exp.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, f in enumerate(frames):
        assert f.rgb is not None and f.depth is not None
        np.save(exp / f"rgb_{i}.npy", f.rgb)
        np.save(exp / f"pc_{i}.npy", deproject(f.depth, camera))
        np.save(exp / f"pressure_{i}.npy", np.float64(f.pressure_pa / HPA))
        w = [0.0] * 6 if f.wrench is None else [float(x) for x in f.wrench]
        rows.append([float(i) / 30.0, f.pressure_pa / HPA, [0.0] * 6, w])
    (path / "data.json").write_text(json.dumps(rows))
    return path


def write_mcap(path: Path, frames: list[Frame], reference: list[Frame], camera: Camera) -> Path:
    """The project's MCAP recording (inputs, wrench channel, reference frames)."""
    from bubble_rt.io.mcap_writer import write_recording

    # Recordings use wall-clock-like times; the simulator's reference frames have t < 0.
    def stamp(fs: list[Frame], t0: float) -> list[Frame]:
        return [replace(f, t=t0 + i / 30.0, t_pressure=t0 + i / 30.0) for i, f in enumerate(fs)]

    write_recording(path, stamp(frames, 1000.0), camera, reference=stamp(reference, 900.0))
    return path


def stiffer_trajectory(
    geometry: str, trajectory: int, n_frames: int, seed: int, factor: float, n_reference: int
) -> SimTrajectory:
    """A dataset trajectory (``bubble_rt.eval.trajectory_scene``) simulated with the membrane's
    Young's modulus scaled by ``factor`` (the scene's ``PhysicsSpec.youngs_modulus_pa``), depth
    beyond the camera's range as invalid (:func:`saturated_to_invalid`)."""
    from bubble_rt.eval import trajectory_scene
    from bubble_rt.sim.simulator import Simulator

    scene = trajectory_scene(geometry, trajectory, n_frames, seed)
    physics = replace(scene.physics, youngs_modulus_pa=factor * scene.physics.youngs_modulus_pa)
    sim = Simulator(replace(scene, physics=physics))
    return SimTrajectory(
        frames=saturated_to_invalid(list(sim.frames())),
        reference_frames=saturated_to_invalid(sim.reference_frames(n_reference)),
        camera=sim.camera,
    )


#: A six-frame scene on the real physics (500 nodes): fast enough for daemon tests.
TINY_SCENE = """
name = "tiny"
seed = 0
frames = 6

[sensor]
camera = "d405"
sim_nodes = 500

[rates]
camera_hz = 30.0
pressure_hz = 100.0

[indenter]
preset = "round"

[trajectory]
loop = true
keyframes = [
  { t = 0.0, at = [0.0, 0.0], depth = -0.002 },
  { t = 0.2, at = [0.0, 0.0], depth = 0.006 },
]

[effects]
gas_compression = true
"""
