"""The scene simulator: physics (cached on disk), rendering, sensor effects, ground truth.

``Simulator(scene).frames()`` yields ``bubble_rt.frames.Frame`` objects with ``truth`` set to a
``GroundTruth``; ``reference_frames(n)`` yields untouched frames for taring. Physics runs once
per scene content and package version and is cached (see cache.py); rendering and effects are
recomputed per frame (about 20 ms at 640 x 480).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh
from bubble_rt.sim import cache, effects
from bubble_rt.sim import oracle as _oracle  # noqa: F401  (registers flow method "oracle")
from bubble_rt.sim.scene import IndenterSpec, Scene, load_scene
from bubble_rt.sim.trajectory import ReferenceSurface, trajectory_poses
from bubble_rt.sim.truth import GroundTruth, SurfaceLocator

log = logging.getLogger(__name__)


def progress_bar(
    desc: str, file: IO[str] | None = None, unit: str = "frame"
) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback for :class:`Simulator` that draws one tqdm bar.

    The bar appears at the first report (a cached physics reports nothing) on ``file`` (default
    stderr, drawn only on a terminal) and closes when ``done`` reaches ``total``. Its count
    never goes back: a report below the count already shown is ignored.
    """
    from tqdm import tqdm

    lock = threading.Lock()
    state: dict[str, Any] = {"bar": None}

    def progress(done: int, total: int) -> None:
        with lock:
            bar = state["bar"]
            if bar is None:
                bar = state["bar"] = tqdm(
                    total=total,
                    desc=desc,
                    unit=unit,
                    leave=False,
                    file=file,
                    disable=None if file is None else False,
                )
            if done > bar.n:
                bar.update(done - bar.n)
            if done >= total:
                bar.close()

    return progress


class PhysicsBackend(Protocol):
    """What the simulator needs from the membrane physics (bubble_rt.sim.physics)."""

    def rest_mesh(self, sim_nodes: int, rest_dome_height_m: float) -> Mesh: ...

    def create(self, scene: Scene, rest_mesh: Mesh) -> Any:
        """An object with ``.inflate() -> state`` and ``.solve(indenter, pose) -> state``."""

    def indenter(self, spec: IndenterSpec) -> Any: ...

    def distance(self, indenter: Any, points: NDArray, pose: NDArray) -> NDArray:
        """Signed distance (m) of mesh-frame points to the indenter placed at ``pose``."""


class DefaultPhysics:
    """Adapter to bubble_rt.sim.physics and bubble_rt.sim.indenters (the simphys engineer's)."""

    def rest_mesh(self, sim_nodes: int, rest_dome_height_m: float) -> Mesh:
        import bubble_rt.sim.physics as physics

        return physics.default_rest_mesh(sim_nodes, rest_dome_height_m=rest_dome_height_m)

    def create(self, scene: Scene, rest_mesh: Mesh) -> Any:
        import bubble_rt.sim.physics as physics

        ph = scene.physics
        material = physics.MembraneMaterial(E=ph.youngs_modulus_pa, thickness=ph.thickness_m)
        gas = physics.GasSettings(
            gauge_pressure_pa=ph.gauge_pressure_pa,
            atmospheric_pa=ph.atmospheric_pa,
            chamber_volume_m3=ph.chamber_volume_m3,
            compressible=scene.has("gas_compression"),
        )
        mu = scene.params("friction")["mu"] if scene.has("friction") else None
        kw: dict[str, Any] = {"friction": mu}
        if ph.penalty is not None:
            kw["penalty"] = ph.penalty
        contact = physics.ContactSettings(**kw)
        return physics.MembraneSim(rest_mesh, material, gas, contact)

    def indenter(self, spec: IndenterSpec) -> Any:
        import bubble_rt.sim.indenters as indenters

        if spec.preset is not None:
            return indenters.preset(spec.preset)
        parts: list[Any] = []
        for s in spec.shapes:
            c = np.asarray(s.center)
            if s.type == "sphere":
                parts.append(indenters.Sphere(s.radius, tuple(c)))
            elif s.type == "capsule":
                ax = np.asarray(s.axis) / np.linalg.norm(s.axis)
                a, b = c - ax * s.length / 2, c + ax * s.length / 2
                parts.append(indenters.Capsule(tuple(a), tuple(b), s.radius))
            else:
                half = tuple(0.5 * np.asarray(s.size))
                parts.append(indenters.Box(half, tuple(c)))
        return parts[0] if len(parts) == 1 else indenters.Union(tuple(parts))

    def distance(self, indenter: Any, points: NDArray, pose: NDArray) -> NDArray:
        d = indenter.distance(points, pose)
        return np.asarray(d[0] if isinstance(d, tuple) else d)


@dataclass
class PhysicsRun:
    """Physics of a whole scene. Per-frame arrays have a leading frames axis.

    rest_vertices: M x 3 rest (uninflated) shape, the material coordinates; triangles T x 3;
    boundary: rim node indices; ref_*: the inflated untouched state; poses F x 4 x 4;
    vertices F x M x 3; contact_forces F x M x 3 (N, on the membrane); contact F x M;
    pressure_pa F (absolute); volume_m3 F; converged F; iterations F.
    """

    rest_vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    boundary: NDArray[np.int32]
    ref_vertices: NDArray[np.float64]
    ref_pressure_pa: float
    ref_volume_m3: float
    poses: NDArray[np.float64]
    vertices: NDArray[np.float64]
    contact_forces: NDArray[np.float64]
    contact: NDArray[np.bool_]
    pressure_pa: NDArray[np.float64]
    volume_m3: NDArray[np.float64]
    converged: NDArray[np.bool_]
    iterations: NDArray[np.int32]

    def to_arrays(self) -> dict[str, NDArray]:
        return {k: np.asarray(v) for k, v in self.__dict__.items()}

    @classmethod
    def from_arrays(cls, a: dict[str, NDArray]) -> PhysicsRun:
        kw: dict[str, Any] = {k: a[k] for k in cls.__dataclass_fields__}
        kw["ref_pressure_pa"] = float(kw["ref_pressure_pa"])
        kw["ref_volume_m3"] = float(kw["ref_volume_m3"])
        return cls(**kw)


@dataclass
class PressureReadings:
    """The pressure sensor's stream: reported timestamps t (s) and readings (Pa, absolute)."""

    t: NDArray[np.float64]
    pressure_pa: NDArray[np.float64]
    t_true: NDArray[np.float64]

    @property
    def pressure_hpa(self) -> NDArray[np.float64]:
        return self.pressure_pa / 100.0


def _state_array(state: Any, name: str) -> NDArray:
    return np.asarray(getattr(state, name))


class Simulator:
    """Simulates a scene.

    Args:
        scene: a Scene, a built-in scene name ("demo") or a TOML path.
        physics: the physics backend (default: bubble_rt.sim.physics); tests pass a fake.
        use_cache: read/write physics results in the on-disk cache.
        progress: called as progress(done, total) while the physics runs (frames solved so
            far, frames in all), from the one thread computing it; see :func:`progress_bar`.
    """

    def __init__(
        self,
        scene: Scene | str | Path,
        physics: PhysicsBackend | None = None,
        use_cache: bool = True,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        self.scene = scene if isinstance(scene, Scene) else load_scene(scene)
        self.physics = physics or DefaultPhysics()
        self.use_cache = use_cache
        self.progress = progress
        s = self.scene.sensor
        cam = Camera.preset(s.camera)
        self.camera: Camera = (
            cam if s.camera_pose is None else cam.with_pose(np.asarray(s.camera_pose))
        )
        self._run: PhysicsRun | None = None
        # Taken while the physics is loaded or computed: threads asking for it at once (the
        # daemon's reference capture and its camera thread) wait for one computation.
        self._run_lock = threading.Lock()
        self._renderer: Any = None
        self._locator: SurfaceLocator | None = None
        #: Names of the stages that actually ran (tests use it to prove unnamed ones did not).
        self.stages_run: set[str] = set()

    # ------------------------------------------------------------------ physics
    def physics_key(self) -> str:
        from bubble_rt import __version__

        return self.scene.physics_key(__version__)

    @property
    def run(self) -> PhysicsRun:
        """The scene's physics, from the cache or computed now (then cached); computed once
        however many threads ask at the same time."""
        if self._run is not None:
            return self._run
        with self._run_lock:
            return self._load_or_simulate()

    def _load_or_simulate(self) -> PhysicsRun:
        if self._run is None:
            key = self.physics_key()
            cached = cache.load(key) if self.use_cache else None
            if cached is not None:
                try:
                    self._run = PhysicsRun.from_arrays(cached)
                except (KeyError, TypeError, ValueError):
                    self._run = None
            if self._run is None:
                self._run = self._simulate_physics()
                if self.use_cache:
                    cache.store(key, self._run.to_arrays())
        return self._run

    def _simulate_physics(self) -> PhysicsRun:
        sc = self.scene
        rest = self.physics.rest_mesh(sc.sensor.sim_nodes, sc.physics.rest_dome_height_m)
        sim = self.physics.create(sc, rest)
        ind = self.physics.indenter(sc.indenter)
        ref = sim.inflate()
        ref_v = _state_array(ref, "vertices").astype(np.float64)
        tris = np.asarray(rest.triangles, dtype=np.int32)
        surface = ReferenceSurface(ref_v, tris)

        def dist(points: NDArray, pose: NDArray) -> NDArray:
            return self.physics.distance(ind, points, pose)

        poses = trajectory_poses(sc.trajectory, sc.frames, sc.rates.camera_hz, surface, dist)
        F, M = sc.frames, len(ref_v)
        out = {
            "vertices": np.empty((F, M, 3)),
            "contact_forces": np.empty((F, M, 3)),
            "contact": np.empty((F, M), bool),
            "pressure_pa": np.empty(F),
            "volume_m3": np.empty(F),
            "converged": np.empty(F, bool),
            "iterations": np.empty(F, np.int32),
        }
        gas_drift = {n: sc.params(n) for n in effects.GAS_DRIFT_EFFECTS if sc.has(n)}
        for n in gas_drift:
            self.stages_run.add(n)
        for i in range(F):
            if gas_drift:
                # The gas law at frame i's drift time: the solve finds the membrane and the
                # chamber pressure at the warmer (or leaked) gas state.
                sim.set_gas_scale(
                    effects.gas_scale(
                        gas_drift.get("gas_temperature_drift"),
                        gas_drift.get("gas_leak"),
                        i / sc.rates.camera_hz * sc.rates.time_scale,
                    )
                )
            st = sim.solve(ind, poses[i])
            out["vertices"][i] = _state_array(st, "vertices")
            out["contact_forces"][i] = _state_array(st, "contact_forces")
            out["contact"][i] = _state_array(st, "contact")
            out["pressure_pa"][i] = float(st.pressure_pa)
            out["volume_m3"][i] = float(st.volume_m3)
            out["converged"][i] = bool(st.converged)
            out["iterations"][i] = int(getattr(st, "iterations", 0))
            if not st.converged:
                log.warning("scene %s frame %d: physics did not converge", sc.name, i)
            if self.progress is not None:
                self.progress(i + 1, F)
        return PhysicsRun(
            rest_vertices=np.asarray(rest.vertices, dtype=np.float64),
            triangles=tris,
            boundary=np.asarray(rest.boundary, dtype=np.int32),
            ref_vertices=ref_v,
            ref_pressure_pa=float(ref.pressure_pa),
            ref_volume_m3=float(ref.volume_m3),
            poses=poses,
            **out,
        )

    # ------------------------------------------------------------------ signals
    def pressure_readings(self) -> PressureReadings:
        """The pressure sensor stream over the scene (rate ``rates.pressure_hz``).

        The true pressure between camera frames is interpolated linearly in time; the named
        pressure and timing effects are applied to the whole series.
        """
        sc, run = self.scene, self.run
        hz = sc.rates.camera_hz
        t_frames = np.arange(sc.frames) / hz
        n = int(np.floor(t_frames[-1] * sc.rates.pressure_hz + 1e-9)) + 1
        t_true = np.arange(n) / sc.rates.pressure_hz
        values = np.interp(t_true, t_frames, run.pressure_pa)
        for name, fn in effects.PRESSURE_STAGES.items():
            if sc.has(name):
                self.stages_run.add(name)
                values = fn(values, sc.params(name), effects.effect_rng(sc.seed, name, 0))
        t = t_true
        if sc.has("timestamp_jitter"):
            self.stages_run.add("timestamp_jitter")
            rng = effects.effect_rng(sc.seed, "timestamp_jitter", 1)
            t = effects.timestamp_jitter(t_true, sc.params("timestamp_jitter"), rng)
        return PressureReadings(t=t, pressure_pa=values, t_true=t_true)

    def _renderer_for(self) -> Any:
        if self._renderer is None:
            from bubble_rt.sim.render import MembraneRenderer
            from bubble_rt.sim.texture import MembraneTexture, TextureSettings

            run = self.run
            sensor = self.scene.sensor
            tex = MembraneTexture(TextureSettings.named(sensor.texture, sensor.texture_seed))
            self._renderer = MembraneRenderer(self.camera, run.triangles, run.rest_vertices, tex)
        return self._renderer

    def truth(self, i: int | None) -> GroundTruth:
        """The ground truth of scene frame ``i`` (``i`` modulo the scene's frames; None: the
        untouched reference), as ``frames()`` and ``reference_frames()`` attach it."""
        return self._truth(None if i is None else int(i) % int(self.scene.frames))

    def _truth(self, i: int | None) -> GroundTruth:
        run = self.run
        if self._locator is None:
            self._locator = SurfaceLocator(run.ref_vertices, run.triangles)
        if i is None:  # the untouched reference
            zeros = np.zeros_like(run.ref_vertices)
            return GroundTruth(
                indenter_pose=np.full((4, 4), np.nan),
                net_force=np.zeros(3),
                node_forces=zeros,
                pressure_pa=run.ref_pressure_pa,
                sim_vertices=run.ref_vertices,
                sim_reference_vertices=run.ref_vertices,
                sim_triangles=run.triangles,
                contact=np.zeros(len(zeros), bool),
                converged=True,
                locator=self._locator,
            )
        interior = np.ones(len(run.ref_vertices), bool)
        interior[run.boundary] = False
        f = run.contact_forces[i]
        return GroundTruth(
            indenter_pose=run.poses[i],
            net_force=f[interior].sum(axis=0),
            node_forces=f,
            pressure_pa=float(run.pressure_pa[i]),
            sim_vertices=run.vertices[i],
            sim_reference_vertices=run.ref_vertices,
            sim_triangles=run.triangles,
            contact=run.contact[i],
            converged=bool(run.converged[i]),
            locator=self._locator,
            interior=interior,
        )

    def _images(
        self, vertices: NDArray, index: int, t: float
    ) -> tuple[NDArray[np.uint8] | None, NDArray[np.float32] | None]:
        sc = self.scene
        if sc.has("oracle"):
            self.stages_run.add("oracle")
            return None, None
        self.stages_run.add("render")
        r = self._renderer_for().render(vertices)
        for name in effects.IMAGE_STAGES:
            if sc.has(name):
                self.stages_run.add(name)
        return effects.apply_image_effects(
            sc.effects, sc.seed, index, t, r.rgb, r.depth, time_scale=sc.rates.time_scale
        )

    def frames(self, loop: bool = False) -> Iterator[Frame]:
        """The scene's frames in order (``loop=True``: repeat forever, times keep increasing,
        noise is fresh each pass). Dropped frames (effect "dropped_frames") leave gaps in
        ``Frame.index``."""
        sc = self.scene
        readings = self.pressure_readings()
        F, hz = sc.frames, sc.rates.camera_hz
        rep = 0
        while True:
            base = rep * F
            idx = np.arange(base, base + F)
            t_true = idx / hz
            keep = np.ones(F, bool)
            if sc.has("dropped_frames"):
                self.stages_run.add("dropped_frames")
                rng = effects.effect_rng(sc.seed, "dropped_frames", rep)
                keep = effects.dropped_frames(F, sc.params("dropped_frames"), rng)
            t_rep = t_true
            if sc.has("timestamp_jitter"):
                self.stages_run.add("timestamp_jitter")
                rng = effects.effect_rng(sc.seed, "timestamp_jitter", 2 + rep)
                t_rep = effects.timestamp_jitter(t_true, sc.params("timestamp_jitter"), rng)
            period = F / hz
            for i in range(F):
                if not keep[i]:
                    continue
                k = int(np.searchsorted(readings.t_true, t_true[i] - rep * period, side="right"))
                k = max(k - 1, 0)
                truth = self._truth(i)
                rgb, depth = self._images(self.run.vertices[i], int(idx[i]), float(t_true[i]))
                yield Frame(
                    rgb=rgb,
                    depth=depth,
                    pressure_pa=float(readings.pressure_pa[k]),
                    t=float(t_rep[i]),
                    t_pressure=float(readings.t[k] + rep * period),
                    wrench=None,
                    truth=truth,
                    index=int(idx[i]),
                    meta={"scene": sc.name, "converged": truth.converged, "source": "sim"},
                )
            if not loop:
                return
            rep += 1

    def reference_frames(self, n: int = 5) -> list[Frame]:
        """``n`` frames of the untouched membrane (before the trajectory starts) for taring."""
        sc, run = self.scene, self.run
        hz = sc.rates.camera_hz
        out = []
        for k in range(n):
            index = effects.REFERENCE_STREAM + k
            t = -(n - k) / hz
            p = np.array([run.ref_pressure_pa])
            for name, fn in effects.PRESSURE_STAGES.items():
                if sc.has(name):
                    p = fn(p, sc.params(name), effects.effect_rng(sc.seed, name, index))
            rgb, depth = self._images(run.ref_vertices, index, t)
            out.append(
                Frame(
                    rgb=rgb,
                    depth=depth,
                    pressure_pa=float(p[0]),
                    t=t,
                    t_pressure=t,
                    truth=self._truth(None),
                    index=-(n - k),
                    meta={"scene": sc.name, "reference": True, "source": "sim"},
                )
            )
        return out


def simulate(scene: Scene | str | Path, **kwargs: Any) -> list[Frame]:
    """All frames of a scene as a list (convenience for small scenes)."""
    return list(Simulator(scene, **kwargs).frames())


__all__ = [
    "DefaultPhysics",
    "PhysicsRun",
    "PressureReadings",
    "Simulator",
    "simulate",
    "load_scene",
]
