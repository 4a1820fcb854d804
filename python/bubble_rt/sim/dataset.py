"""The paper's dataset procedure, as scenes.

For each indenter (round, point, line, square, split) and trajectory: pick a contact point on
the dome, an approach direction sampled around the inward surface normal (equivalently, a
sensor orientation roughly facing the indenter, fixed along the trajectory) and a spin about
it; then move from a free-space waypoint to one near the surface to one in contact. Half the
trajectories are light touches (a shallow final depth, about 1 N), half heavy (a deep one,
10 N and more). Everything derives from one seed, so the set is reproducible.

``DatasetSettings.profile`` names the sensor profile whose bubble (physics, camera and pose)
the scenes simulate; ``PUNYO_DEPTHS`` are final depths for the stiffer simulated Punyo.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bubble_rt.sensor import PROFILES
from bubble_rt.sim.effect_names import EFFECT_DEFAULTS
from bubble_rt.sim.scene import (
    INDENTER_PRESETS,
    IndenterSpec,
    Keyframe,
    PhysicsSpec,
    RatesSpec,
    Scene,
    SensorSpec,
    TrajectorySpec,
)

#: Final depths past first touch (m; light, firm) on the simulated Punyo (``profile = "punyo"``),
#: whose membrane needs about three times the ``sim`` bubble's force for a dent: light touches
#: of about 0.3-1.5 N and firm presses of about 2-6 N, the real press's range (4.8 N at 5.5 mm).
PUNYO_DEPTHS: tuple[tuple[str, tuple[tuple[float, float], tuple[float, float]]], ...] = (
    ("round", ((0.0008, 0.002), (0.0035, 0.006))),
    ("point", ((0.0012, 0.003), (0.005, 0.008))),
    ("line", ((0.0006, 0.0015), (0.0025, 0.0045))),
    ("square", ((0.0005, 0.0012), (0.002, 0.0035))),
    ("split", ((0.0008, 0.0018), (0.003, 0.005))),
)


@dataclass(frozen=True)
class DatasetSettings:
    """How to sample trajectories (lengths in metres, angles in degrees).

    Attributes:
        per_indenter: trajectories per indenter (the paper: 34).
        frames: frames per trajectory (the paper: 100).
        indenters: indenter presets to use.
        seed: master seed (each trajectory's scene seed derives from it).
        footprint_fraction: contact points lie within this fraction of the rim ellipse.
        max_tilt_deg: approach direction within this angle of the inward normal.
        free_gap: (min, max) gap of the free-space waypoint; lateral offset up to free_offset.
        near_gap: (min, max) gap of the near waypoint.
        depths: per indenter, ((min, max) light, (min, max) heavy) final depth past first
            touch (m). Defaults from a straight-press sweep of the physics at the dome top
            (1,200 nodes; docs/simulator.md): about 1 N and 10 N+ (the point pin reaches ~6 N at
            22 mm, the deepest press the 30 mm dome allows).
        heavy_fraction: share of heavy touches (alternating, so both are always present).
        effects: effects every trajectory scene names.
        sim_nodes: physics mesh resolution.
        profile: the sensor profile (``bubble_rt.sensor``) whose bubble the scenes simulate
            (its physics, camera and camera pose); pair ``"punyo"`` with ``PUNYO_DEPTHS``.
    """

    per_indenter: int = 34
    frames: int = 100
    indenters: tuple[str, ...] = INDENTER_PRESETS
    seed: int = 0
    footprint_fraction: float = 0.35
    max_tilt_deg: float = 15.0
    free_gap: tuple[float, float] = (0.010, 0.020)
    free_offset: float = 0.008
    near_gap: tuple[float, float] = (0.001, 0.003)
    depths: tuple[tuple[str, tuple[tuple[float, float], tuple[float, float]]], ...] = (
        ("round", ((0.0025, 0.004), (0.022, 0.026))),
        ("point", ((0.003, 0.005), (0.020, 0.024))),
        ("line", ((0.0018, 0.003), (0.016, 0.020))),
        ("square", ((0.0015, 0.003), (0.017, 0.021))),
        ("split", ((0.0018, 0.003), (0.018, 0.022))),
    )
    heavy_fraction: float = 0.5
    effects: tuple[str, ...] = (
        "friction",
        "gas_compression",
        "depth_noise",
        "depth_dropouts",
        "depth_jumps",
        "rgb_noise",
        "pressure_noise",
        "pressure_quantization",
    )
    sim_nodes: int = 2000
    rates: RatesSpec = field(default_factory=RatesSpec)
    profile: str = "sim"


def _tilted(rng: np.random.Generator, max_tilt_deg: float) -> tuple[float, float, float]:
    """A unit direction within max_tilt of (0, 0, -1), uniform on the spherical cap."""
    c = rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0)
    s = np.sqrt(1 - c * c)
    phi = rng.uniform(0, 2 * np.pi)
    return (float(s * np.cos(phi)), float(s * np.sin(phi)), float(-c))


def trajectory_scene(
    indenter: str, k: int, settings: DatasetSettings, rng: np.random.Generator
) -> Scene:
    """One sampled trajectory as a scene (named "<indenter>-<k>")."""
    st = settings
    a, b = 0.05725, 0.040
    r = st.footprint_fraction * np.sqrt(rng.uniform(0, 1))
    th = rng.uniform(0, 2 * np.pi)
    at = (float(a * r * np.cos(th)), float(b * r * np.sin(th)))
    # Approach: a direction within max_tilt of the inward normal of the nominal dome there.
    from bubble_rt.mesh import MeshGeometry
    from bubble_rt.sim.trajectory import rotation_pressing_along

    gx, gy = MeshGeometry().slope(np.array(at[0]), np.array(at[1]))
    inward = -np.array([-float(gx), -float(gy), 1.0])
    inward /= np.linalg.norm(inward)
    local = np.array(_tilted(rng, st.max_tilt_deg))
    # rotation_pressing_along maps (0, 0, -1) onto the inward normal; apply it to the tilt.
    ax, ay, az = (float(x) for x in rotation_pressing_along(inward, 0.0) @ local)
    approach = (ax, ay, az)
    spin = float(rng.uniform(0, 360))
    off = rng.normal(size=2)
    off = off / max(float(np.linalg.norm(off)), 1e-12) * rng.uniform(0, st.free_offset)
    heavy = (k % 2 == 1) if st.heavy_fraction == 0.5 else bool(rng.random() < st.heavy_fraction)
    light, deep = dict(st.depths)[indenter]
    depth = float(rng.uniform(*(deep if heavy else light)))
    free_gap = float(rng.uniform(*st.free_gap))
    near_gap = float(rng.uniform(*st.near_gap))
    duration = (st.frames - 1) / st.rates.camera_hz
    kf = (
        Keyframe(
            t=0.0,
            at=(at[0] + float(off[0]), at[1] + float(off[1])),
            depth=-free_gap,
            approach=approach,
            spin_deg=spin,
        ),
        Keyframe(t=0.35 * duration, at=at, depth=-near_gap, approach=approach, spin_deg=spin),
        Keyframe(t=0.85 * duration, at=at, depth=depth, approach=approach, spin_deg=spin),
        Keyframe(t=duration, at=at, depth=depth, approach=approach, spin_deg=spin),
    )
    effects = tuple((e, tuple(sorted(EFFECT_DEFAULTS[e].items()))) for e in st.effects)
    bubble = PROFILES[st.profile].bubble
    return Scene(
        name=f"{indenter}-{k}",
        trajectory=TrajectorySpec(keyframes=kf, loop=False),
        frames=st.frames,
        seed=int(rng.integers(0, 2**31 - 1)),
        sensor=SensorSpec(
            camera=bubble.camera,
            camera_pose=bubble.camera_pose,
            sim_nodes=st.sim_nodes,
            texture=bubble.texture,
        ),
        rates=st.rates,
        physics=PhysicsSpec.of(bubble),
        indenter=IndenterSpec(preset=indenter),
        effects=effects,
        profile=st.profile,
    )


def dataset_scenes(settings: DatasetSettings | None = None) -> list[Scene]:
    """All trajectory scenes (per indenter, in order), reproducible from ``settings.seed``."""
    st = settings or DatasetSettings()
    out = []
    for j, name in enumerate(st.indenters):
        rng = np.random.default_rng([st.seed, j])
        for k in range(st.per_indenter):
            out.append(trajectory_scene(name, k, st, rng))
    return out
