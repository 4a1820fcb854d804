"""Scenes: what to simulate, read from TOML.

A scene names the sensor profile (``profile``: "sim", the default, or "punyo"; its bubble,
``bubble_rt.sensor.BubblePhysics``, gives the defaults of ``[physics]`` and of the camera), the
sensor, the physics settings, the indenter, its trajectory, the effects to
simulate (nothing else is computed), the seed and the number of frames. Built-in scenes ship in
``bubble_rt/scenes/*.toml`` and are loaded by name (``load_scene("demo")``); any other argument
is read as a file path. Errors raise ``SceneError`` naming the offending key (e.g.
``trajectory.keyframes[2].depth``).
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from bubble_rt.sensor import PROFILES, SIM_BUBBLE, BubblePhysics
from bubble_rt.sim.effect_names import EFFECT_DEFAULTS, GAS_DRIFT_EFFECTS, IMAGE_EFFECTS

INDENTER_PRESETS = ("round", "point", "line", "square", "split")
SHAPE_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("radius",),
    "capsule": ("radius", "length"),
    "box": ("size",),
}


class SceneError(ValueError):
    """A scene is malformed; the message names the key at fault."""


@dataclass(frozen=True)
class SensorSpec:
    """camera: camera preset name; camera_pose: optional 4 x 4 camera-to-mesh transform;
    sim_nodes: node count of the physics mesh; texture: the membrane's pattern
    (``bubble_rt.sim.texture.PATTERNS``; the profile's bubble's unless given); texture_seed:
    its random draw."""

    camera: str = "d405"
    camera_pose: tuple[tuple[float, ...], ...] | None = None
    sim_nodes: int = 2000
    texture_seed: int = 0
    texture: str = SIM_BUBBLE.texture


@dataclass(frozen=True)
class RatesSpec:
    """camera_hz: camera frame rate; pressure_hz: pressure sensor reading rate (Hz);
    time_scale: drift seconds per scene second, the time compression of the slow-drift
    effects (gas temperature, leak, illumination: 60 plays an hour of drift in a minute;
    the indenter and the membrane still move at scene speed)."""

    camera_hz: float = 30.0
    pressure_hz: float = 100.0
    time_scale: float = 1.0


@dataclass(frozen=True)
class PhysicsSpec:
    """Membrane, gas and contact settings (SI units): operating gauge pressure and ambient
    pressure (Pa), chamber volume behind the membrane (m^3), Young's modulus (Pa), membrane
    thickness (m), contact penalty (N/m^2; None: the physics default). Friction (the Coulomb
    coefficient, effect parameter ``mu``) and gas compressibility only take effect when the
    effects "friction" / "gas_compression" are named."""

    gauge_pressure_pa: float = SIM_BUBBLE.gauge_pressure_pa
    atmospheric_pa: float = SIM_BUBBLE.ambient_pa
    chamber_volume_m3: float = SIM_BUBBLE.chamber_volume_m3
    youngs_modulus_pa: float = SIM_BUBBLE.youngs_modulus_pa
    thickness_m: float = SIM_BUBBLE.thickness_m
    penalty: float | None = None
    #: Apex (m) of the stress-free dome (``bubble_rt.sim.physics.default_rest_mesh``).
    rest_dome_height_m: float = SIM_BUBBLE.rest_dome_height_m

    @classmethod
    def of(cls, bubble: BubblePhysics) -> PhysicsSpec:
        """The physics of a sensor profile's bubble."""
        return cls(
            gauge_pressure_pa=bubble.gauge_pressure_pa,
            atmospheric_pa=bubble.ambient_pa,
            chamber_volume_m3=bubble.chamber_volume_m3,
            youngs_modulus_pa=bubble.youngs_modulus_pa,
            thickness_m=bubble.thickness_m,
            rest_dome_height_m=bubble.rest_dome_height_m,
        )


#: PhysicsSpec fields added after caches keyed on the others existed: at these values they stay
#: out of ``Scene.physics_key``, so the physics of existing scenes keeps its cache entry.
_KEY_FREE_DEFAULTS: dict[str, float] = {"rest_dome_height_m": SIM_BUBBLE.rest_dome_height_m}


@dataclass(frozen=True)
class ShapeSpec:
    """One primitive of a user indenter, in the indenter frame (m)."""

    type: str
    radius: float = 0.0
    length: float = 0.0
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)


@dataclass(frozen=True)
class IndenterSpec:
    """Either a preset name or a union of shapes (indenter frame: it presses along its -z)."""

    preset: str | None = "round"
    shapes: tuple[ShapeSpec, ...] = ()


@dataclass(frozen=True)
class Keyframe:
    """An indenter pose at time t (s).

    Surface form: ``at`` (x, y) picks the reference-surface point above that footprint point;
    the indenter approaches along ``approach`` (unit, mesh frame; default: the inward surface
    normal there), spun by ``spin_deg`` about it, and ``depth`` (m) is how far it is pushed past
    first touch (negative: a gap). Pose form: ``position`` (m) and ``rotvec`` (rad).
    """

    t: float
    at: tuple[float, float] | None = None
    depth: float = 0.0
    approach: tuple[float, float, float] | None = None
    spin_deg: float = 0.0
    position: tuple[float, float, float] | None = None
    rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class TrajectorySpec:
    keyframes: tuple[Keyframe, ...]
    loop: bool = False


@dataclass(frozen=True)
class Scene:
    """A validated scene. ``effects`` maps each named effect to its full parameter set."""

    name: str
    trajectory: TrajectorySpec
    frames: int
    seed: int = 0
    sensor: SensorSpec = field(default_factory=SensorSpec)
    rates: RatesSpec = field(default_factory=RatesSpec)
    physics: PhysicsSpec = field(default_factory=PhysicsSpec)
    indenter: IndenterSpec = field(default_factory=IndenterSpec)
    effects: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = ()
    #: The sensor profile (``bubble_rt.sensor``) whose bubble this scene simulates.
    profile: str = "sim"

    # ------------------------------------------------------------------ queries
    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.effects)

    def has(self, effect: str) -> bool:
        return effect in self.effect_names

    def params(self, effect: str) -> dict[str, float]:
        for name, p in self.effects:
            if name == effect:
                return dict(p)
        raise KeyError(effect)

    def with_changes(self, **changes: Any) -> Scene:
        from dataclasses import replace

        return replace(self, **changes)

    def physics_key(self, version: str) -> str:
        """Hash of everything the physics depends on, plus the package version and the physics
        revision (``bubble_rt.sim.physics.PHYSICS_REVISION``)."""
        # Imported here: the physics pulls in NumPy/SciPy, and scenes load without them.
        from bubble_rt.sim.physics import PHYSICS_REVISION

        payload = {
            "version": version,
            "physics_revision": PHYSICS_REVISION,
            "sim_nodes": self.sensor.sim_nodes,
            "physics": {
                k: v
                for k, v in asdict(self.physics).items()
                if not (k in _KEY_FREE_DEFAULTS and v == _KEY_FREE_DEFAULTS[k])
            },
            "indenter": asdict(self.indenter),
            "trajectory": asdict(self.trajectory),
            "frames": self.frames,
            "camera_hz": self.rates.camera_hz,
            "friction": self.params("friction") if self.has("friction") else None,
            "gas": self.has("gas_compression"),
        }
        # The gas drift changes the physics; named only when present, so other scenes keep
        # their cache entries.
        drift = {n: self.params(n) for n in GAS_DRIFT_EFFECTS if self.has(n)}
        if drift:
            payload["gas_drift"] = drift
            payload["time_scale"] = self.rates.time_scale
        blob = json.dumps(payload, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:32]


# ---------------------------------------------------------------------- loading
def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with the package."""
    root = resources.files("bubble_rt") / "scenes"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def load_scene(name_or_path: str | Path) -> Scene:
    """A built-in scene by name ("demo") or a TOML file by path."""
    s = str(name_or_path)
    if not s.endswith(".toml") and s in builtin_scenes():
        text = (resources.files("bubble_rt") / "scenes" / f"{s}.toml").read_text()
        return parse_scene(text, default_name=s)
    path = Path(s)
    if not path.exists():
        raise SceneError(
            f"scene {s!r} is neither a built-in ({', '.join(builtin_scenes())}) nor a file"
        )
    return parse_scene(path.read_text(), default_name=path.stem)


def parse_scene(text: str, default_name: str = "scene") -> Scene:
    """Parse and validate a scene's TOML text."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"scene is not valid TOML: {exc}") from exc
    return scene_from_dict(data, default_name)


def _num(d: dict, key: str, path: str, default: Any = None, positive: bool = False) -> Any:
    if key not in d:
        if default is None:
            raise SceneError(f"{path}{key}: missing (required)")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise SceneError(f"{path}{key}: expected a number, got {v!r}")
    if positive and not v > 0:
        raise SceneError(f"{path}{key}: must be positive, got {v!r}")
    return float(v)


def _int(d: dict, key: str, path: str, default: int | None = None, minimum: int = 0) -> int:
    if key not in d:
        if default is None:
            raise SceneError(f"{path}{key}: missing (required)")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise SceneError(f"{path}{key}: expected an integer, got {v!r}")
    if v < minimum:
        raise SceneError(f"{path}{key}: must be at least {minimum}, got {v}")
    return int(v)


def _vec(d: dict, key: str, path: str, n: int, default: Any = None) -> Any:
    if key not in d:
        if default is None and n > 0:
            raise SceneError(f"{path}{key}: missing (required)")
        return default
    v = d[key]
    if (
        not isinstance(v, list)
        or len(v) != n
        or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v)
    ):
        raise SceneError(f"{path}{key}: expected a list of {n} numbers, got {v!r}")
    return tuple(float(x) for x in v)


def _table(data: dict, key: str) -> dict:
    v = data.get(key, {})
    if not isinstance(v, dict):
        raise SceneError(f"{key}: expected a table, got {v!r}")
    return v


def _no_unknown(d: dict, allowed: tuple[str, ...], path: str) -> None:
    for k in d:
        if k not in allowed:
            raise SceneError(f"{path}{k}: unknown key; allowed: {', '.join(allowed)}")


def scene_from_dict(data: dict[str, Any], default_name: str = "scene") -> Scene:
    """Validate a parsed scene (the TOML as a dict)."""
    _no_unknown(
        data,
        (
            "name",
            "profile",
            "seed",
            "frames",
            "sensor",
            "rates",
            "physics",
            "indenter",
            "trajectory",
            "effects",
        ),
        "",
    )
    name = data.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise SceneError(f"name: expected a non-empty string, got {name!r}")
    seed = _int(data, "seed", "", 0)
    prof = data.get("profile", "sim")
    if not isinstance(prof, str) or prof not in PROFILES:
        raise SceneError(f"profile: unknown sensor profile {prof!r}; known: {', '.join(PROFILES)}")
    bubble = PROFILES[prof].bubble
    rd = _table(data, "rates")
    _no_unknown(rd, ("camera_hz", "pressure_hz", "time_scale"), "rates.")
    rates = RatesSpec(
        camera_hz=_num(rd, "camera_hz", "rates.", 30.0, positive=True),
        pressure_hz=_num(rd, "pressure_hz", "rates.", 100.0, positive=True),
        time_scale=_num(rd, "time_scale", "rates.", 1.0, positive=True),
    )
    trajectory = _parse_trajectory(data.get("trajectory"))
    t_end = trajectory.keyframes[-1].t
    return Scene(
        name=name,
        trajectory=trajectory,
        frames=_int(data, "frames", "", int(round(t_end * rates.camera_hz)) + 1, minimum=1),
        seed=seed,
        sensor=_parse_sensor(_table(data, "sensor"), bubble),
        rates=rates,
        physics=_parse_physics(_table(data, "physics"), bubble),
        indenter=_parse_indenter(_table(data, "indenter")),
        effects=_parse_scene_effects(data.get("effects", [])),
        profile=prof,
    )


def _parse_sensor(sd: dict, bubble: BubblePhysics) -> SensorSpec:
    """``[sensor]``: the camera preset and pose (the profile's unless given), the simulation
    mesh's node count, the texture (the profile's unless given) and its seed."""
    from bubble_rt.camera import Camera
    from bubble_rt.sim.texture import PATTERNS

    _no_unknown(sd, ("camera", "camera_pose", "sim_nodes", "texture", "texture_seed"), "sensor.")
    texture = sd.get("texture", bubble.texture)
    if not isinstance(texture, str) or texture not in PATTERNS:
        raise SceneError(
            f"sensor.texture: unknown texture {texture!r}; known: {', '.join(PATTERNS)}"
        )
    camera = sd.get("camera", bubble.camera)
    try:
        Camera.preset(camera)
    except (ValueError, TypeError) as exc:
        raise SceneError(f"sensor.camera: {exc}") from exc
    pose = sd.get("camera_pose", bubble.camera_pose)
    if pose is not None:
        if not (
            isinstance(pose, list | tuple)
            and len(pose) == 4
            and all(isinstance(r, list | tuple) and len(r) == 4 for r in pose)
        ):
            raise SceneError("sensor.camera_pose: expected a 4 x 4 list of numbers")
        try:
            Camera.preset(camera, pose=tuple(tuple(float(x) for x in r) for r in pose))
        except (ValueError, TypeError) as exc:
            raise SceneError(f"sensor.camera_pose: {exc}") from exc
        pose = tuple(tuple(float(x) for x in r) for r in pose)
    return SensorSpec(
        camera=camera,
        camera_pose=pose,
        sim_nodes=_int(sd, "sim_nodes", "sensor.", 2000, minimum=50),
        texture_seed=_int(sd, "texture_seed", "sensor.", 0),
        texture=texture,
    )


def _parse_physics(pd: dict, bubble: BubblePhysics) -> PhysicsSpec:
    """``[physics]``: each key defaults to the profile's bubble (``PhysicsSpec.of``)."""
    _no_unknown(pd, tuple(PhysicsSpec.__dataclass_fields__), "physics.")
    dflt = PhysicsSpec.of(bubble)
    return PhysicsSpec(
        gauge_pressure_pa=_num(pd, "gauge_pressure_pa", "physics.", dflt.gauge_pressure_pa, True),
        atmospheric_pa=_num(pd, "atmospheric_pa", "physics.", dflt.atmospheric_pa, True),
        chamber_volume_m3=_num(pd, "chamber_volume_m3", "physics.", dflt.chamber_volume_m3, True),
        youngs_modulus_pa=_num(pd, "youngs_modulus_pa", "physics.", dflt.youngs_modulus_pa, True),
        thickness_m=_num(pd, "thickness_m", "physics.", dflt.thickness_m, True),
        penalty=_num(pd, "penalty", "physics.", positive=True) if "penalty" in pd else None,
        rest_dome_height_m=_num(
            pd, "rest_dome_height_m", "physics.", dflt.rest_dome_height_m, True
        ),
    )


def _parse_scene_effects(spec: Any) -> tuple[tuple[str, tuple[tuple[str, float], ...]], ...]:
    """``[effects]``, and the combinations that cannot work refused."""
    effects = _parse_effects(spec)
    named = dict(effects)
    if "oracle" in named and any(n in named for n in IMAGE_EFFECTS):
        raise SceneError(
            "effects: 'oracle' renders no image, so it cannot be combined with image effects"
        )
    for n in GAS_DRIFT_EFFECTS:
        if n in named and "gas_compression" not in named:
            raise SceneError(
                f"effects.{n}: the gas drifts only when it is sealed; name 'gas_compression' too"
            )
    return effects


def _parse_indenter(d: dict) -> IndenterSpec:
    _no_unknown(d, ("preset", "shapes"), "indenter.")
    if "preset" in d and "shapes" in d:
        raise SceneError("indenter: give either 'preset' or 'shapes', not both")
    if "shapes" not in d:
        preset = d.get("preset", "round")
        if preset not in INDENTER_PRESETS:
            raise SceneError(
                f"indenter.preset: unknown preset {preset!r}; choose one of "
                f"{', '.join(INDENTER_PRESETS)}"
            )
        return IndenterSpec(preset=preset)
    shapes = d["shapes"]
    if not isinstance(shapes, list) or not shapes:
        raise SceneError("indenter.shapes: expected a non-empty list of tables")
    out = []
    for i, s in enumerate(shapes):
        path = f"indenter.shapes[{i}]."
        if not isinstance(s, dict):
            raise SceneError(f"indenter.shapes[{i}]: expected a table")
        kind = s.get("type")
        if kind not in SHAPE_KEYS:
            raise SceneError(f"{path}type: expected one of {', '.join(SHAPE_KEYS)}, got {kind!r}")
        _no_unknown(s, ("type", "center", "axis") + SHAPE_KEYS[kind], path)
        kw: dict[str, Any] = {"type": kind}
        kw["center"] = _vec(s, "center", path, 3, (0.0, 0.0, 0.0))
        if kind == "sphere":
            kw["radius"] = _num(s, "radius", path, positive=True)
        elif kind == "capsule":
            kw["radius"] = _num(s, "radius", path, positive=True)
            kw["length"] = _num(s, "length", path, positive=True)
            kw["axis"] = _vec(s, "axis", path, 3, (1.0, 0.0, 0.0))
        else:
            size = _vec(s, "size", path, 3)
            if min(size) <= 0:
                raise SceneError(f"{path}size: every side must be positive, got {list(size)}")
            kw["size"] = size
        out.append(ShapeSpec(**kw))
    return IndenterSpec(preset=None, shapes=tuple(out))


def _parse_trajectory(d: Any) -> TrajectorySpec:
    if d is None:
        raise SceneError("trajectory: missing (required table with 'keyframes')")
    if not isinstance(d, dict):
        raise SceneError("trajectory: expected a table")
    _no_unknown(d, ("keyframes", "loop"), "trajectory.")
    loop = d.get("loop", False)
    if not isinstance(loop, bool):
        raise SceneError(f"trajectory.loop: expected true or false, got {loop!r}")
    kfs = d.get("keyframes")
    if not isinstance(kfs, list) or not kfs:
        raise SceneError("trajectory.keyframes: expected a non-empty list of tables")
    out: list[Keyframe] = []
    allowed = ("t", "at", "depth", "approach", "spin_deg", "position", "rotvec")
    for i, k in enumerate(kfs):
        path = f"trajectory.keyframes[{i}]."
        if not isinstance(k, dict):
            raise SceneError(f"trajectory.keyframes[{i}]: expected a table")
        _no_unknown(k, allowed, path)
        t = _num(k, "t", path)
        if out and t <= out[-1].t:
            raise SceneError(f"{path}t: times must increase, got {t} after {out[-1].t}")
        if t < 0:
            raise SceneError(f"{path}t: must be >= 0, got {t}")
        if ("at" in k) == ("position" in k):
            raise SceneError(f"{path}at: give exactly one of 'at' (surface form) or 'position'")
        if "at" in k:
            approach = _vec(k, "approach", path, 3, None) if "approach" in k else None
            if approach is not None and sum(x * x for x in approach) < 1e-12:
                raise SceneError(f"{path}approach: must be a non-zero direction")
            out.append(
                Keyframe(
                    t=t,
                    at=_vec(k, "at", path, 2),
                    depth=_num(k, "depth", path, 0.0),
                    approach=approach,
                    spin_deg=_num(k, "spin_deg", path, 0.0),
                )
            )
        else:
            if any(x in k for x in ("depth", "approach", "spin_deg")):
                raise SceneError(f"{path}depth: 'depth/approach/spin_deg' need the 'at' form")
            out.append(
                Keyframe(
                    t=t,
                    position=_vec(k, "position", path, 3),
                    rotvec=_vec(k, "rotvec", path, 3, (0.0, 0.0, 0.0)),
                )
            )
    forms = {kf.at is None for kf in out}
    if len(forms) > 1:
        raise SceneError("trajectory.keyframes: do not mix the 'at' and 'position' forms")
    return TrajectorySpec(keyframes=tuple(out), loop=loop)


def _parse_effects(e: Any) -> tuple[tuple[str, tuple[tuple[str, float], ...]], ...]:
    if isinstance(e, list):
        items: list[tuple[str, dict]] = []
        for i, name in enumerate(e):
            if not isinstance(name, str):
                raise SceneError(f"effects[{i}]: expected an effect name, got {name!r}")
            items.append((name, {}))
    elif isinstance(e, dict):
        items = []
        for name, p in e.items():
            if isinstance(p, bool) and p:
                p = {}
            if not isinstance(p, dict):
                raise SceneError(f"effects.{name}: expected a table of parameters (or true)")
            items.append((name, p))
    else:
        raise SceneError("effects: expected a list of names or a table of name -> parameters")
    out = []
    seen = set()
    for name, p in items:
        if name not in EFFECT_DEFAULTS:
            raise SceneError(
                f"effects.{name}: unknown effect; choose from {', '.join(EFFECT_DEFAULTS)}"
            )
        if name in seen:
            raise SceneError(f"effects.{name}: named twice")
        seen.add(name)
        params = dict(EFFECT_DEFAULTS[name])
        for k, v in p.items():
            if k not in params:
                allowed = ", ".join(params) or "none"
                raise SceneError(f"effects.{name}.{k}: unknown parameter; allowed: {allowed}")
            if isinstance(v, bool) or not isinstance(v, int | float) or v < 0:
                raise SceneError(f"effects.{name}.{k}: expected a non-negative number, got {v!r}")
            params[k] = float(v)
        out.append((name, tuple(sorted(params.items()))))
    return tuple(out)
