"""Evaluation tasks: simulated trajectories run through each estimator, and recordings."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.eval.fanout import run_tasks
from bubble_rt.eval.metrics import (
    ESTIMATORS,
    FrameMetrics,
    frame_metrics,
    patch_scores,
    summarize,
)

#: Seeds for evaluation trajectories start here; calibration uses seeds below it.
EVAL_SEED_BASE = 100_000
CALIB_SEED_BASE = 1_000


# ---------------------------------------------------------------------------------- tasks
@dataclass(frozen=True)
class EvalTask:
    """One simulated trajectory to evaluate (plain data, picklable).

    Attributes:
        geometry: indenter name (round, point, line, square, split).
        seed: the dataset's master seed (EVAL_SEED_BASE; calibration uses CALIB_SEED_BASE, so
            the two sets never share a trajectory).
        trajectory: index within its geometry (the dataset scene "<geometry>-<trajectory>").
        n_frames: frames per trajectory.
        mesh: estimator mesh preset name or node count.
        estimators: which estimators to run.
        flow_method: FlowSettings.method for the deformation tracker ("oracle" skips rendering).
        config: estimator overrides (k_f, k_u, E) as plain floats.
        keep_fields: keep per-node fields of these frame indices (for figures).
        n_reference: untouched frames averaged into the reference capture.
        physics: simulator physics backend (None: the real one; tests pass a stand-in).
    """

    geometry: str
    seed: int
    trajectory: int = 0
    n_frames: int = 20
    mesh: str = "medium"
    estimators: tuple[str, ...] = ESTIMATORS
    flow_method: str = "default"
    config: tuple[tuple[str, float], ...] = ()
    keep_fields: tuple[int, ...] = ()
    n_reference: int = 5
    physics: Any = None


@dataclass
class TrajectoryResult:
    """What one EvalTask produced: per-frame metrics and optional fields for figures."""

    task: EvalTask
    records: list[FrameMetrics]
    seconds: float
    fields: dict[str, Any] = field(default_factory=dict)


#: Evaluation overrides name Young's modulus "E" (the calibrated parameter); the [estimator]
#: key is "youngs_modulus".
_E_KEY = "youngs_modulus"


def estimator_config(overrides: Sequence[tuple[str, float]] | dict[str, float]) -> Any:
    """An EstimatorConfig with ``[estimator]`` parameters overridden (``E`` names
    ``youngs_modulus``, as calibration does; other names are ignored)."""
    from dataclasses import replace

    from bubble_rt.estimation.estimator import CONFIG_KEYS, EstimatorConfig, config_changes

    cfg = EstimatorConfig()
    named = {(_E_KEY if k == "E" else k): v for k, v in dict(overrides).items()}
    values = {k: v for k, v in named.items() if k in CONFIG_KEYS}
    return replace(cfg, **config_changes(cfg, values)) if values else cfg


def load_config_overrides(path: str | Path | None) -> dict[str, float]:
    """The estimator parameters a configuration file sets (the daemon's TOML or `bubble-rt
    calibrate`'s output), named as evaluation names them (its [estimator] keys, E for
    youngs_modulus); {} when no path is given. The file goes through the one configuration
    loader (``DaemonConfig.load``), so an unknown key or an out-of-range value raises
    ``ConfigError`` naming it."""
    if not path:
        return {}
    import tomllib

    from bubble_rt.config import DaemonConfig
    from bubble_rt.estimation.estimator import CONFIG_KEYS

    cfg = DaemonConfig.load(path)
    present = tomllib.loads(Path(path).read_text()).get("estimator", {})
    return {
        ("E" if key == _E_KEY else key): getattr(cfg.estimator, key)
        for key in CONFIG_KEYS
        if key in present
    }


def make_tasks(
    geometries: Sequence[str],
    trajectories: int,
    frames: int,
    *,
    seed_base: int = EVAL_SEED_BASE,
    **kw: Any,
) -> list[EvalTask]:
    """Tasks for ``trajectories`` trajectories per geometry with disjoint seeds."""
    tasks = []
    for g in geometries:
        for k in range(trajectories):
            tasks.append(
                EvalTask(
                    geometry=g,
                    seed=seed_base,
                    trajectory=k,
                    n_frames=frames,
                    **kw,
                )
            )
    return tasks


@dataclass
class SimTrajectory:
    """A simulated trajectory: untouched reference frames, then the frames to evaluate."""

    frames: list[Any]
    reference_frames: list[Any]
    camera: Any
    reference_surface: Any = None


def trajectory_scene(geometry: str, trajectory: int, n_frames: int, seed: int) -> Any:
    """Scene of trajectory ``trajectory`` of ``geometry`` in the paper's dataset procedure
    (bubble_rt.sim.dataset) with master seed ``seed``."""
    from bubble_rt.sim.dataset import DatasetSettings, dataset_scenes

    st = DatasetSettings(per_indenter=trajectory + 1, frames=n_frames, seed=seed)
    name = f"{geometry}-{trajectory}"
    for scene in dataset_scenes(st):
        if scene.name == name:
            return scene
    raise ValueError(f"no trajectory {name!r} in the dataset (unknown indenter {geometry!r}?)")


def simulate_trajectory(
    geometry: str,
    trajectory: int,
    n_frames: int,
    seed: int,
    *,
    n_reference: int = 5,
    render: bool = True,
    physics: Any = None,
) -> SimTrajectory:
    """Simulate one dataset trajectory: reference frames and the trajectory's frames.

    ``render=False`` adds the simulator's "oracle" effect (no images; the deformation tracker's
    "oracle" method reads the truth's displacement field instead), dropping image effects.
    ``physics``: a simulator physics backend (default: the real one; tests pass a stand-in).
    """
    from dataclasses import replace

    from bubble_rt.sim.effect_names import IMAGE_EFFECTS
    from bubble_rt.sim.simulator import Simulator

    scene = trajectory_scene(geometry, trajectory, n_frames, seed)
    if not render:
        # "oracle" renders no image, so no image effect may go with it (Scene's own rule).
        kept = tuple(e for e in scene.effects if e[0] not in IMAGE_EFFECTS)
        scene = replace(scene, effects=kept + (("oracle", ()),))
    sim = Simulator(scene, physics=physics)
    refs = sim.reference_frames(n_reference)
    frames = list(sim.frames())
    return SimTrajectory(frames=frames, reference_frames=refs, camera=sim.camera)


def estimator_mesh(name: str, traj: SimTrajectory) -> Any:
    """The estimator mesh (preset name or node count): fitted onto the reference surface seen
    by the camera when the reference frames have depth."""
    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.estimation.pipeline import fitted_mesh

    reference = Reference.capture(traj.reference_frames)
    return fitted_mesh(str(name), reference, traj.camera, fit=reference.depth is not None)


def flow_settings(method: str = "default") -> Any:
    """FlowSettings of a method name ("default": FlowSettings' own)."""
    from bubble_rt.estimation.deformation import FlowSettings

    return FlowSettings() if method == "default" else FlowSettings(method=method)


def build_pipeline(
    kind: str, mesh: Any, traj: SimTrajectory, config: Any, flow_method: str = "default"
) -> Any:
    """The estimation Pipeline of estimator ``kind`` on ``mesh`` (from ``estimator_mesh``) for
    this trajectory's camera and reference frames."""
    from bubble_rt.estimation.pipeline import Pipeline

    return Pipeline.capture(
        traj.reference_frames,
        traj.camera,
        mesh=mesh,
        fit=False,
        kind=kind,
        config=config,
        flow=flow_settings(flow_method),
    )


def build_estimator(
    kind: str, mesh: Any, traj: SimTrajectory, config: Any, flow_method: str = "default"
) -> Any:
    """An estimator with ``.process(frame)`` for this trajectory (its Pipeline)."""
    return build_pipeline(kind, mesh, traj, config, flow_method)


def evaluate_trajectory(task: EvalTask) -> TrajectoryResult:
    """Simulate one trajectory, run each estimator on every frame, score against the truth."""
    from bubble_rt.estimation.registry import estimator_kind

    t0 = time.perf_counter()
    traj = simulate_trajectory(
        task.geometry,
        task.trajectory,
        task.n_frames,
        task.seed,
        n_reference=task.n_reference,
        # kinds that read the frames themselves (the frictionless baseline) need depth images,
        # so render for them even with "oracle" tracking
        render=task.flow_method != "oracle"
        or not all(estimator_kind(e).tracked for e in task.estimators),
        physics=task.physics,
    )
    mesh = estimator_mesh(task.mesh, traj)
    areas = mesh.lumped_areas()
    normals = mesh.vertex_normals()
    interior = np.ones(mesh.n_nodes, bool)
    interior[mesh.boundary] = False
    gt_masks = [np.asarray(f.truth.contact_mask(mesh), dtype=bool) for f in traj.frames]
    from bubble_rt.wrench import PatchFinder

    finder = PatchFinder(mesh)  # the patches and torque the daemon would publish
    true_patches = [f.truth.patches() for f in traj.frames]
    config = estimator_config(task.config)
    records: list[FrameMetrics] = []
    fields: dict[str, Any] = {
        "vertices": mesh.vertices,
        "triangles": mesh.triangles,
        "boundary": mesh.boundary,
    }
    for name in task.estimators:
        est = build_estimator(name, mesh, traj, config, task.flow_method)
        for i, frame in enumerate(traj.frames):
            ts = time.perf_counter()
            e = est.process(frame)
            ms = 1e3 * (time.perf_counter() - ts)
            f_gt = np.asarray(frame.truth.net_force, dtype=float)
            patches = finder.patches_of(e)
            ps = patch_scores(patches, true_patches[i])
            rec = replace(
                frame_metrics(
                    geometry=task.geometry,
                    estimator=name,
                    trajectory=task.trajectory,
                    frame=i,
                    f_est=np.asarray(e.net_force, dtype=float),
                    f_gt=f_gt,
                    est_contact=np.asarray(e.contact, dtype=bool),
                    gt_contact=gt_masks[i],
                    normals=normals,
                    areas=areas,
                    interior=interior,
                    time_ms=ms,
                    truth_converged=bool(getattr(frame.truth, "converged", True)),
                ),
                tau_est=[float(x) for x in finder.net_torque_of(e)],
                tau_gt=[float(x) for x in frame.truth.net_torque()],
                tau_gt_reference=[float(x) for x in frame.truth.net_torque(at_reference=True)],
                centroid_err_mm=ps.centroid_err_mm,
                pressure_centroid_err_mm=ps.pressure_centroid_err_mm,
                patch_area_ratio=ps.area_ratio,
                two_contact=ps.two_contact,
                two_found=ps.two_found,
                two_found_magnitude=ps.two_found_magnitude,
                est_patches=len(patches),
            )
            records.append(rec)
            if i in task.keep_fields:
                fields.setdefault("frames", {}).setdefault(i, {})[name] = {
                    "node_forces": np.asarray(e.node_forces, dtype=float),
                    "contact": np.asarray(e.contact, dtype=bool),
                    "gt_contact": gt_masks[i],
                }
    return TrajectoryResult(task, records, time.perf_counter() - t0, fields)


# ---------------------------------------------------------------------------------- driver
def run_eval(
    tasks: Sequence[EvalTask],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
) -> tuple[list[TrajectoryResult], dict[str, Any]]:
    """Evaluate all tasks; returns the trajectory results and the summary (with throughput)."""
    t0 = time.perf_counter()
    results = run_tasks(
        evaluate_trajectory,
        tasks,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc="eval",
    )
    wall = time.perf_counter() - t0
    records = [rec for r in results for rec in r.records]
    summary = summarize(records)
    n_frames = sum(t.n_frames for t in tasks)
    busy = sum(r.seconds for r in results)
    summary["throughput"] = {
        "frames": n_frames,
        "wall_s": wall,
        "frames_per_s": n_frames / wall if wall > 0 else float("nan"),
        "frames_per_s_per_worker": n_frames / busy if busy > 0 else float("nan"),
        "workers": workers if not scheduler else None,
        "scheduler": scheduler,
    }
    return list(results), summary


QUICK_FRAMES = 8
#: the default evaluation: trajectories per indenter and frames per trajectory (400 frames)
DEFAULT_TRAJECTORIES = 4
DEFAULT_FRAMES = 20


# ---------------------------------------------------------------------------------- recordings
def evaluate_recording(
    path: str | Path,
    *,
    overrides: dict[str, float] | None = None,
    estimators: Sequence[str] = ("fem",),
    mesh: str = "medium",
    n_reference: int = 5,
    force_threshold: float = 1.0,
    max_frames: int | None = None,
    bag_options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Net-force magnitude error and contact detection on a real recording with a wrench.

    The wrench is in the arm's frame, so only magnitudes are compared:
    ``| |f_net| - |w_f - bias| |`` with ``bias`` the mean wrench force over the reference
    frames. The reference is the one the recording holds (this project's MCAP recordings: up to
    ``n_reference`` of the untouched frames its daemon captured before its stream, as
    ``calibrate`` and ``estimate`` take it; every stream frame is then scored), else its first
    ``n_reference`` frames, which are not scored. A frame counts as touched when
    ``|w_f - bias| > force_threshold`` (N); the estimate detects contact when it marks any
    contact node. Reports mean/median magnitude error, accuracy, precision, recall and the
    false-contact rate on untouched frames, per estimator.
    """
    from bubble_rt.io.recordings import open_recording

    # bag_options: ROS 2 bags only; an MCAP recording also holds its reference frames
    rec: Any = open_recording(path, **(bag_options or {}))
    frames = list(rec)
    if max_frames:
        frames = frames[:max_frames]
    recorded = bool(getattr(rec, "has_reference", False))
    if recorded:
        ref_frames = list(rec.reference_frames(max(1, n_reference)))
        scored = frames
    else:
        if len(frames) <= n_reference:
            n_reference = max(1, len(frames) // 2)
        ref_frames = frames[:n_reference]
        scored = frames[n_reference:] if len(frames) > n_reference else frames
    if not ref_frames or not scored:
        raise ValueError(f"{path}: no frame to evaluate (a reference and a frame to score)")
    if any(f.wrench is None for f in [*ref_frames, *scored]):
        raise ValueError(f"{path}: recording has frames without a wrench")
    bias = np.asarray([f.wrench for f in ref_frames], dtype=float)[:, :3].mean(axis=0)
    W = np.asarray([f.wrench for f in scored], dtype=float)[:, :3]
    f_gt = np.linalg.norm(W - bias, axis=1)
    touched = f_gt > force_threshold
    from bubble_rt.sensor import profile_for_layout

    # The recording's sensor profile (a Punyo folder or bag: the Punyo's; an MCAP recording:
    # the one its daemon ran with), unless overridden.
    ambient = {"ambient_pa": profile_for_layout(getattr(rec, "layout", "")).ambient_pa}
    config = estimator_config({**ambient, **(overrides or {})})
    out: dict[str, Any] = {
        "recording": str(path),
        "frames": len(scored),
        "reference_frames": len(ref_frames),
        "reference": "recorded" if recorded else "first frames",
        "force_threshold_n": force_threshold,
        "ambient_pa": config.ambient_pa,
        "touched_frames": int(touched.sum()),
        "estimators": {},
    }
    traj = SimTrajectory(frames=frames, reference_frames=ref_frames, camera=rec.camera)
    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.estimation.pipeline import fitted_mesh

    fitted = fitted_mesh(str(mesh), Reference.capture(ref_frames), rec.camera)
    for name in estimators:
        est = build_estimator(name, fitted, traj, config)
        out["estimators"][name] = _score_recording(est, scored, f_gt, touched)
    return out


def _score_recording(
    est: Any, scored: Sequence[Any], f_gt: NDArray[np.float64], touched: NDArray[np.bool_]
) -> dict[str, Any]:
    """One estimator on a recording's scored frames: net-force magnitude error against the
    wrench (N), contact detection against ``touched``, median time per frame (ms)."""
    mags, det, ms = [], [], []
    for fr in scored:
        t0 = time.perf_counter()
        e = est.process(fr)
        ms.append(1e3 * (time.perf_counter() - t0))
        mags.append(float(np.linalg.norm(e.net_force)))
        det.append(bool(np.asarray(e.contact).any()))
    m = np.asarray(mags)
    d = np.asarray(det)
    err = np.abs(m - f_gt)
    tp = int((d & touched).sum())
    fp = int((d & ~touched).sum())
    fn = int((~d & touched).sum())
    return {
        "force_mag_err_n": float(err.mean()),
        "force_mag_err_median_n": float(np.median(err)),
        "force_mag_err_touched_n": float(err[touched].mean()) if touched.any() else None,
        "accuracy": float((d == touched).mean()),
        "precision": tp / (tp + fp) if tp + fp else None,
        "recall": tp / (tp + fn) if tp + fn else None,
        "false_contact_rate": float(d[~touched].mean()) if (~touched).any() else None,
        "mean_force_n": float(m.mean()),
        "time_ms": float(np.median(ms)),
    }
