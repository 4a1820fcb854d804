"""Accuracy of the force/contact estimators against ground truth.

Metrics (all per frame, aggregated per geometry and estimator):

- Contact IoU over the estimator's mesh nodes: ``|est & gt| / |est | gt|``. A frame where neither
  the estimate nor the ground truth has a contact node has no defined IoU and is left out of the
  mean (mIoU = mean over frames with contact in the truth or in the estimate). A frame where only
  one side has contact scores 0. Rim nodes take part like any other node (the estimator never
  marks them, the truth rarely does).
- Net-force error ``|f - f_gt|`` (N), with f the force the object applies on the membrane.
- Normal and shear error: the error vector ``e = f - f_gt`` split along the contact normal
  ``n_c`` (unit, pointing into the membrane, i.e. the direction an indenter pushes):
  ``normal = |e . n_c|``, ``shear = |e - (e . n_c) n_c|``, so ``normal^2 + shear^2 = |e|^2``.
  ``n_c`` is minus the area-weighted mean outward normal over the ground-truth contact nodes;
  when the truth has no contact node, over the estimated contact nodes; when neither has any,
  over all interior nodes (the dome's mean normal, about -z).
- Light-touch detection rate: among frames whose ground truth is in contact with a net force
  below 1.5 N, the fraction where the estimate marks at least one contact node.
- False contacts: among untouched frames (no ground-truth contact node), the fraction where the
  estimate marks any contact node; ``false_nodes`` is the mean number of such nodes.

Force errors are averaged over all frames of a trajectory (untouched ones included), as the
paper's table does; ``force_err_contact_n`` averages over in-contact frames only.

Frames whose simulated ground truth did not converge (``truth.converged`` False: the physics
step failed even in substeps) are still run through the estimators, so warm starts see the
whole trajectory, but are left out of every statistic and counted in ``n_excluded``: a force
the simulator itself flags as unreliable is no ground truth.

The fan-out helper :func:`run_tasks` maps a picklable function over tasks on a local process
pool (``workers``) or, given a Dask scheduler address, on a Dask distributed cluster.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

LIGHT_TOUCH_N = 1.5
GEOMETRIES = ("round", "point", "line", "square", "split")
ESTIMATORS = ("fem", "frictionless")
#: Seeds for evaluation trajectories start here; calibration uses seeds below it.
EVAL_SEED_BASE = 100_000
CALIB_SEED_BASE = 1_000

T = TypeVar("T")
R = TypeVar("R")


# ---------------------------------------------------------------------------------- geometry
def lumped_areas(vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> NDArray:
    """Lumped node areas (N,), m^2: one third of every incident triangle's area."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    a = np.zeros(len(v))
    for k in range(3):
        np.add.at(a, t[:, k], area / 3.0)
    return a


def vertex_normals(vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> NDArray:
    """Area-weighted outward unit normals (N x 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], cross)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


# ---------------------------------------------------------------------------------- metrics
def contact_iou(estimate: NDArray[np.bool_], truth: NDArray[np.bool_]) -> float:
    """IoU of two node masks; NaN when both are empty (the frame has no defined IoU)."""
    e = np.asarray(estimate, dtype=bool)
    g = np.asarray(truth, dtype=bool)
    if e.shape != g.shape:
        raise ValueError(f"contact masks differ in shape: {e.shape} vs {g.shape}")
    union = int(np.count_nonzero(e | g))
    if union == 0:
        return float("nan")
    return int(np.count_nonzero(e & g)) / union


def contact_normal(
    normals: NDArray[np.float64],
    areas: NDArray[np.float64],
    truth: NDArray[np.bool_],
    estimate: NDArray[np.bool_] | None = None,
    interior: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """Unit contact normal (3,) pointing into the membrane (the direction an indenter pushes).

    Minus the area-weighted mean outward normal over the ground-truth contact nodes; falls back
    to the estimated contact nodes, then to all interior nodes (see the module docstring).
    """
    n = np.asarray(normals, dtype=np.float64)
    a = np.asarray(areas, dtype=np.float64)
    candidates = [np.asarray(truth, dtype=bool)]
    if estimate is not None:
        candidates.append(np.asarray(estimate, dtype=bool))
    candidates.append(
        np.ones(len(n), bool) if interior is None else np.asarray(interior, dtype=bool)
    )
    for mask in candidates:
        if mask.any():
            m = -(a[mask, None] * n[mask]).sum(axis=0)
            norm = float(np.linalg.norm(m))
            if norm > 0:
                return m / norm
    return np.array([0.0, 0.0, -1.0])


def split_force_error(
    f_est: NDArray[np.float64], f_gt: NDArray[np.float64], normal: NDArray[np.float64]
) -> tuple[float, float, float]:
    """(total, normal, shear) magnitudes (N) of ``f_est - f_gt`` w.r.t. the unit ``normal``."""
    e = np.asarray(f_est, dtype=np.float64) - np.asarray(f_gt, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    en = float(e @ n)
    shear = e - en * n
    return float(np.linalg.norm(e)), abs(en), float(np.linalg.norm(shear))


@dataclass
class FrameMetrics:
    """Per-frame evaluation record (forces in N, time in ms)."""

    geometry: str
    estimator: str
    trajectory: int
    frame: int
    iou: float
    force_err_n: float
    normal_err_n: float
    shear_err_n: float
    f_est: list[float]
    f_gt: list[float]
    gt_contact: bool
    est_contact: bool
    gt_nodes: int
    est_nodes: int
    false_nodes: int
    time_ms: float = float("nan")
    truth_converged: bool = True


def frame_metrics(
    *,
    geometry: str,
    estimator: str,
    trajectory: int,
    frame: int,
    f_est: NDArray[np.float64],
    f_gt: NDArray[np.float64],
    est_contact: NDArray[np.bool_],
    gt_contact: NDArray[np.bool_],
    normals: NDArray[np.float64],
    areas: NDArray[np.float64],
    interior: NDArray[np.bool_] | None = None,
    time_ms: float = float("nan"),
    truth_converged: bool = True,
) -> FrameMetrics:
    """All per-frame metrics for one estimate against its ground truth."""
    e = np.asarray(est_contact, dtype=bool)
    g = np.asarray(gt_contact, dtype=bool)
    n_c = contact_normal(normals, areas, g, e, interior)
    total, normal, shear = split_force_error(f_est, f_gt, n_c)
    return FrameMetrics(
        geometry=geometry,
        estimator=estimator,
        trajectory=int(trajectory),
        frame=int(frame),
        iou=contact_iou(e, g),
        force_err_n=total,
        normal_err_n=normal,
        shear_err_n=shear,
        f_est=[float(x) for x in np.asarray(f_est, dtype=float)],
        f_gt=[float(x) for x in np.asarray(f_gt, dtype=float)],
        gt_contact=bool(g.any()),
        est_contact=bool(e.any()),
        gt_nodes=int(g.sum()),
        est_nodes=int(e.sum()),
        false_nodes=int(np.count_nonzero(e & ~g)),
        time_ms=float(time_ms),
        truth_converged=bool(truth_converged),
    )


def _nanmean(values: Iterable[float]) -> float:
    arr = np.asarray([v for v in values if not math.isnan(v)], dtype=float)
    return float(arr.mean()) if arr.size else float("nan")


def aggregate(records: Sequence[FrameMetrics]) -> dict[str, float]:
    """Summary statistics of a group of frame records (see the module docstring)."""
    recs = [r for r in records if r.truth_converged]
    n_excluded = len(records) - len(recs)
    light = [r for r in recs if r.gt_contact and float(np.linalg.norm(r.f_gt)) < LIGHT_TOUCH_N]
    untouched = [r for r in recs if not r.gt_contact]
    contact = [r for r in recs if r.gt_contact]
    return {
        "miou": _nanmean(r.iou for r in recs),
        "force_err_n": _nanmean(r.force_err_n for r in recs),
        "normal_err_n": _nanmean(r.normal_err_n for r in recs),
        "shear_err_n": _nanmean(r.shear_err_n for r in recs),
        "force_err_contact_n": _nanmean(r.force_err_n for r in contact),
        "light_touch_rate": (
            sum(r.est_contact for r in light) / len(light) if light else float("nan")
        ),
        "false_contact_rate": (
            sum(r.est_contact for r in untouched) / len(untouched) if untouched else float("nan")
        ),
        "false_nodes": _nanmean(float(r.false_nodes) for r in untouched),
        "time_ms": _nanmean(r.time_ms for r in recs),
        "n_frames": float(len(recs)),
        "n_light": float(len(light)),
        "n_untouched": float(len(untouched)),
        "n_excluded": float(n_excluded),
    }


SUMMARY_KEYS = (
    "miou",
    "force_err_n",
    "normal_err_n",
    "shear_err_n",
    "force_err_contact_n",
    "light_touch_rate",
    "false_contact_rate",
    "false_nodes",
    "time_ms",
)


def summarize(records: Sequence[FrameMetrics]) -> dict[str, Any]:
    """``{"geometries": {g: {est: stats}}, "average": {est: stats}}``.

    The average is the unweighted mean over geometries of each statistic (as the paper's table),
    ignoring geometries where a statistic is undefined.
    """
    geoms: dict[str, dict[str, dict[str, float]]] = {}
    order_g = [g for g in GEOMETRIES if any(r.geometry == g for r in records)]
    order_g += sorted({r.geometry for r in records} - set(order_g))
    order_e = [e for e in ESTIMATORS if any(r.estimator == e for r in records)]
    order_e += sorted({r.estimator for r in records} - set(order_e))
    for g in order_g:
        geoms[g] = {}
        for e in order_e:
            sel = [r for r in records if r.geometry == g and r.estimator == e]
            if sel:
                geoms[g][e] = aggregate(sel)
    average: dict[str, dict[str, float]] = {}
    for e in order_e:
        per = [geoms[g][e] for g in geoms if e in geoms[g]]
        stats = {k: _nanmean(p[k] for p in per) for k in SUMMARY_KEYS}
        stats["n_frames"] = float(sum(p["n_frames"] for p in per))
        stats["n_excluded"] = float(sum(p["n_excluded"] for p in per))
        average[e] = stats
    return {"geometries": geoms, "average": average}


def _fmt(x: float, digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown_table(summary: dict[str, Any]) -> str:
    """The accuracy table: one row per geometry (and the average), columns per estimator."""
    ests: list[str] = list(summary["average"].keys())
    cols = [
        ("mIoU", "miou", 3),
        ("force err (N)", "force_err_n", 2),
        ("normal err (N)", "normal_err_n", 2),
        ("shear err (N)", "shear_err_n", 2),
        ("light-touch det.", "light_touch_rate", 2),
        ("false contact", "false_contact_rate", 2),
    ]
    header = ["geometry"] + [f"{e} {c[0]}" for e in ests for c in cols] + ["frames"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    rows = list(summary["geometries"].items()) + [("average", summary["average"])]
    for name, per in rows:
        cells = [name]
        n, x = 0.0, 0.0
        for e in ests:
            st = per.get(e)
            for _, key, d in cols:
                cells.append(_fmt(st[key], d) if st else "-")
            if st:
                n = max(n, st["n_frames"])
                x = max(x, st.get("n_excluded", 0.0))
        cells.append(str(int(n)) + (f" (+{int(x)} excluded)" if x else ""))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def records_to_json(records: Sequence[FrameMetrics]) -> list[dict[str, Any]]:
    return [asdict(r) for r in records]


def _json_clean(obj: Any) -> Any:
    """NaN -> None so the file is strict JSON."""
    if isinstance(obj, float):
        return None if math.isnan(obj) or math.isinf(obj) else obj
    if isinstance(obj, dict):
        return {k: _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    return obj


def write_json(path: str | Path, payload: dict[str, Any]) -> None:
    import json

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(_json_clean(payload), indent=2, allow_nan=False) + "\n")


# ---------------------------------------------------------------------------------- fan-out
class FanOut:
    """Maps picklable functions over tasks: inline, on a process pool, or on a Dask cluster.

    ``workers <= 1`` and no scheduler runs inline (no pickling). Given ``scheduler`` (a Dask
    scheduler address, e.g. ``tcp://host:8786`` or a LocalCluster's address) the same tasks run
    on that cluster. The pool / client lives until :meth:`close` (use as a context manager), so
    repeated maps (an optimiser's loss evaluations) reuse warm workers and their caches.
    """

    def __init__(self, workers: int = 1, scheduler: str | None = None) -> None:
        self.workers = max(1, int(workers))
        self.scheduler = scheduler or None
        self._pool: Any = None
        self._client: Any = None
        if self.scheduler:
            from dask.distributed import Client

            self._client = Client(self.scheduler, set_as_default=False)
        elif self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # fork keeps start-up cheap; workers build their own estimators (C++ state is
            # never shared across the fork because nothing heavy is built before it).
            methods = mp.get_all_start_methods()
            ctx = mp.get_context("fork") if "fork" in methods else None
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx)

    @property
    def parallelism(self) -> int:
        if self._client is not None:
            info = self._client.scheduler_info()
            return max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))
        return self.workers

    def map(
        self,
        fn: Callable[[T], R],
        tasks: Sequence[T],
        *,
        progress: bool = False,
        desc: str = "tasks",
    ) -> list[R]:
        """``[fn(t) for t in tasks]`` in order."""
        tasks = list(tasks)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(tasks), desc=desc, unit="task", leave=False)
        try:
            out: dict[int, R] = {}
            if self._client is not None:
                futures = self._client.map(fn, tasks, pure=False)
                # Collected in submission order: the cluster still runs them concurrently.
                for i, fut in enumerate(futures):
                    out[i] = fut.result()
                    if bar is not None:
                        bar.update(1)
            elif self._pool is not None and len(tasks) > 1:
                from concurrent.futures import as_completed as cf_completed

                fmap = {self._pool.submit(fn, t): i for i, t in enumerate(tasks)}
                for fut in cf_completed(fmap):
                    out[fmap[fut]] = fut.result()
                    if bar is not None:
                        bar.update(1)
            else:
                for i, t in enumerate(tasks):
                    out[i] = fn(t)
                    if bar is not None:
                        bar.update(1)
            return [out[i] for i in range(len(tasks))]
        finally:
            if bar is not None:
                bar.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> FanOut:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_tasks(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    desc: str = "tasks",
) -> list[R]:
    """One-shot :class:`FanOut` map: ``[fn(t) for t in tasks]`` in order."""
    with FanOut(workers=min(workers, max(1, len(tasks))), scheduler=scheduler) as fan:
        return fan.map(fn, tasks, progress=progress, desc=desc)


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


def estimator_config(overrides: Sequence[tuple[str, float]] | dict[str, float]) -> Any:
    """An EstimatorConfig with k_f, k_u, k_const, k_linear and material E overridden."""
    from dataclasses import replace

    from bubble_rt.estimator import EstimatorConfig

    cfg = EstimatorConfig()
    ov = dict(overrides)
    if "E" in ov:
        cfg = replace(cfg, material=replace(cfg.material, E=float(ov.pop("E"))))
    known: dict[str, Any] = {
        k: float(v) for k, v in ov.items() if k in ("k_f", "k_u", "k_const", "k_linear")
    }
    return replace(cfg, **known) if known else cfg


def load_config_overrides(path: str | Path | None) -> dict[str, float]:
    """Read [estimator] k_f, k_u, youngs_modulus (or E), k_const, k_linear from a TOML file
    (the daemon's config or `bubble-rt calibrate`'s output); {} when no path is given."""
    if not path:
        return {}
    import tomllib

    data = tomllib.loads(Path(path).read_text())
    est = data.get("estimator", {})
    out: dict[str, float] = {}
    for k in ("k_f", "k_u", "k_const", "k_linear", "E"):
        if k in est:
            out[k] = float(est[k])
    if "youngs_modulus" in est:  # the daemon config's name for E
        out["E"] = float(est["youngs_modulus"])
    mat = est.get("material", {})
    if isinstance(mat, dict) and "E" in mat:
        out["E"] = float(mat["E"])
    return out


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

    from bubble_rt.sim.simulator import Simulator

    scene = trajectory_scene(geometry, trajectory, n_frames, seed)
    if not render:
        image_effects = {"depth_noise", "depth_dropouts", "rgb_noise", "rgb_blur", "exposure"}
        kept = tuple(e for e in scene.effects if e[0] not in image_effects)
        scene = replace(scene, effects=kept + (("oracle", ()),))
    sim = Simulator(scene, physics=physics)
    refs = sim.reference_frames(n_reference)
    frames = list(sim.frames())
    return SimTrajectory(frames=frames, reference_frames=refs, camera=sim.camera)


def estimator_mesh(name: str, traj: SimTrajectory) -> Any:
    """The estimator mesh: the preset fitted onto the reference surface seen by the camera."""
    from bubble_rt.mesh import Mesh

    template = Mesh.preset(name) if not str(name).isdigit() else Mesh.generate(int(name))
    if traj.reference_frames and traj.reference_frames[0].depth is not None:
        from bubble_rt.deformation import Reference
        from bubble_rt.fitting import fit_mesh

        return fit_mesh(template, Reference.capture(traj.reference_frames), traj.camera)
    return template


def build_estimator(
    kind: str, mesh: Any, traj: SimTrajectory, config: Any, flow_method: str = "default"
) -> Any:
    """An estimator with ``.process(frame)`` for this trajectory's camera and reference."""
    from bubble_rt.deformation import DeformationTracker, FlowSettings, Reference
    from bubble_rt.estimator import make_estimator

    reference = Reference.capture(traj.reference_frames)
    est = make_estimator(kind, mesh, config, camera=traj.camera, reference=reference)
    if kind == "fem":
        settings = FlowSettings() if flow_method == "default" else FlowSettings(method=flow_method)
        est.attach(DeformationTracker(mesh, traj.camera, reference, settings))
    return est


def evaluate_trajectory(task: EvalTask) -> TrajectoryResult:
    """Simulate one trajectory, run each estimator on every frame, score against the truth."""
    t0 = time.perf_counter()
    traj = simulate_trajectory(
        task.geometry,
        task.trajectory,
        task.n_frames,
        task.seed,
        n_reference=task.n_reference,
        # the frictionless baseline always needs depth images, so render even for "oracle"
        render=task.flow_method != "oracle" or any(e != "fem" for e in task.estimators),
        physics=task.physics,
    )
    mesh = estimator_mesh(task.mesh, traj)
    areas = lumped_areas(mesh.vertices, mesh.triangles)
    normals = vertex_normals(mesh.vertices, mesh.triangles)
    interior = np.ones(mesh.n_nodes, bool)
    interior[mesh.boundary] = False
    gt_masks = [np.asarray(f.truth.contact_mask(mesh), dtype=bool) for f in traj.frames]
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
            records.append(
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
                )
            )
            if i in task.keep_fields:
                fields.setdefault("frames", {}).setdefault(i, {})[name] = {
                    "node_forces": np.asarray(e.node_forces, dtype=float),
                    "contact": np.asarray(e.contact, dtype=bool),
                    "gt_contact": gt_masks[i],
                }
    return TrajectoryResult(task, records, time.perf_counter() - t0, fields)


# ---------------------------------------------------------------------------------- figures
def save_figures(
    results: Sequence[TrajectoryResult], out_dir: str | Path, estimators: Sequence[str]
) -> list[Path]:
    """PNG figures: contact patch vs truth, force field arrows, net force vs truth over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    # Per indenter, the trajectory with fields and the largest true force (a heavy touch).
    by_geom: dict[str, TrajectoryResult] = {}

    def peak(r: TrajectoryResult) -> float:
        return max((float(np.linalg.norm(x.f_gt)) for x in r.records), default=0.0)

    for r in results:
        cur = by_geom.get(r.task.geometry)
        has = bool(r.fields.get("frames"))
        if cur is None or (has, peak(r)) > (bool(cur.fields.get("frames")), peak(cur)):
            by_geom[r.task.geometry] = r
    for g, r in by_geom.items():
        # net force vs ground truth over the trajectory
        fig, axes = plt.subplots(1, 4, figsize=(14, 3.2), sharex=True)
        for name in estimators:
            recs = sorted((x for x in r.records if x.estimator == name), key=lambda x: x.frame)
            if not recs:
                continue
            fe = np.array([x.f_est for x in recs])
            fg = np.array([x.f_gt for x in recs])
            idx = [x.frame for x in recs]
            for k, lab in enumerate("xyz"):
                axes[k].plot(idx, fe[:, k], label=name)
                axes[k].set_title(f"f_{lab} (N)")
            axes[3].plot(idx, np.linalg.norm(fe, axis=1), label=name)
            if name == estimators[0]:
                for k in range(3):
                    axes[k].plot(idx, fg[:, k], "k--", label="truth")
                axes[3].plot(idx, np.linalg.norm(fg, axis=1), "k--", label="truth")
        axes[3].set_title("|f| (N)")
        axes[3].legend(fontsize=7)
        for ax in axes:
            ax.set_xlabel("frame")
        fig.suptitle(f"{g}: net force vs ground truth (trajectory {r.task.trajectory})")
        fig.tight_layout()
        p = out / f"net_force_{g}.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        written.append(p)

        frames = r.fields.get("frames", {})
        if not frames:
            continue
        V = np.asarray(r.fields["vertices"])
        i_best = max(frames, key=lambda i: int(next(iter(frames[i].values()))["gt_contact"].sum()))
        per = frames[i_best]
        names = [e for e in estimators if e in per]
        T = np.asarray(r.fields["triangles"])
        interior = np.ones(len(V), bool)
        interior[np.asarray(r.fields.get("boundary", []), dtype=int)] = False
        fig = plt.figure(figsize=(5.2 * len(names), 8.5))
        for j, name in enumerate(names):
            d = per[name]
            est, gt = d["contact"], d["gt_contact"]
            ax = fig.add_subplot(2, len(names), j + 1)
            ax.scatter(V[:, 0] * 1e3, V[:, 1] * 1e3, s=4, c="0.85")
            for mask, col, lab in (
                (est & gt, "tab:green", "both"),
                (est & ~gt, "tab:red", "estimate only"),
                (~est & gt, "tab:blue", "truth only"),
            ):
                ax.scatter(V[mask, 0] * 1e3, V[mask, 1] * 1e3, s=14, c=col, label=lab)
            ax.set_aspect("equal")
            ax.set_title(f"{name}: contact, frame {i_best}, IoU {contact_iou(est, gt):.2f}")
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
            ax.legend(fontsize=7, loc="upper right")
            # Force field: arrows on the mesh (interior nodes; the rim carries the base's
            # reaction), longest arrow drawn 15 mm long.
            ax3 = fig.add_subplot(2, len(names), len(names) + j + 1, projection="3d")
            F = np.asarray(d["node_forces"])
            ax3.plot_trisurf(
                V[:, 0] * 1e3, V[:, 1] * 1e3, V[:, 2] * 1e3, triangles=T, color="0.8", alpha=0.3
            )
            Fi = np.where(interior[:, None], F, 0.0)
            fmax = float(np.linalg.norm(Fi, axis=1).max()) or 1.0
            sc = 15.0 / fmax
            ax3.quiver(
                V[interior, 0] * 1e3,
                V[interior, 1] * 1e3,
                V[interior, 2] * 1e3,
                Fi[interior, 0] * sc,
                Fi[interior, 1] * sc,
                Fi[interior, 2] * sc,
                color=np.where(est[interior], "tab:red", "tab:gray"),
                linewidth=0.8,
                arrow_length_ratio=0.25,
            )
            ax3.set_title(f"{name}: node forces (max {fmax:.2f} N; red = contact)", fontsize=9)
            ax3.set_xlabel("x (mm)")
            ax3.set_ylabel("y (mm)")
            ax3.set_zlabel("z (mm)")
            ax3.view_init(elev=35, azim=-60)
            ext = np.ptp(V, axis=0) * 1e3
            ax3.set_box_aspect((ext[0], ext[1], ext[2] + 15.0))
        fig.tight_layout()
        p = out / f"contact_{g}.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        written.append(p)
    return written


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
) -> dict[str, Any]:
    """Net-force magnitude error and contact detection on a real recording with a wrench.

    The wrench is in the arm's frame, so only magnitudes are compared:
    ``| |f_net| - |w_f - bias| |`` with ``bias`` the mean wrench force over the first
    ``n_reference`` frames (which are also the untouched reference and are not scored). A frame
    counts as touched when ``|w_f - bias| > force_threshold`` (N); the estimate detects contact
    when it marks any contact node. Reports mean/median magnitude error, accuracy, precision, recall and the
    false-contact rate on untouched frames, per estimator.
    """
    from bubble_rt.deformation import Reference
    from bubble_rt.fitting import fit_mesh
    from bubble_rt.mesh import Mesh
    from bubble_rt.recordings import open_recording

    rec = open_recording(path)
    frames = list(rec)
    if max_frames:
        frames = frames[:max_frames]
    if len(frames) <= n_reference:
        n_reference = max(1, len(frames) // 2)
    ref_frames = frames[:n_reference]
    reference = Reference.capture(ref_frames)
    template = Mesh.preset(mesh) if not str(mesh).isdigit() else Mesh.generate(int(mesh))
    fitted = fit_mesh(template, reference, rec.camera)
    wrenches = [f.wrench for f in frames]
    if any(w is None for w in wrenches):
        raise ValueError(f"{path}: recording has frames without a wrench")
    W = np.asarray(wrenches, dtype=float)[:, :3]
    bias = W[:n_reference].mean(axis=0)
    scored = frames[n_reference:] if len(frames) > n_reference else frames
    f_gt = np.linalg.norm(W - bias, axis=1)[len(frames) - len(scored) :]
    touched = f_gt > force_threshold
    config = estimator_config(overrides or {})
    out: dict[str, Any] = {
        "recording": str(path),
        "frames": len(scored),
        "reference_frames": n_reference,
        "force_threshold_n": force_threshold,
        "touched_frames": int(touched.sum()),
        "estimators": {},
    }
    traj = SimTrajectory(frames=frames, reference_frames=ref_frames, camera=rec.camera)
    for name in estimators:
        est = build_estimator(name, fitted, traj, config)
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
        out["estimators"][name] = {
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
    return out


def recording_table(res: dict[str, Any]) -> str:
    """Markdown table for :func:`evaluate_recording`."""
    cols = [
        ("force-magnitude err (N)", "force_mag_err_n"),
        ("err on touched (N)", "force_mag_err_touched_n"),
        ("accuracy", "accuracy"),
        ("precision", "precision"),
        ("recall", "recall"),
        ("false contact", "false_contact_rate"),
        ("ms/frame", "time_ms"),
    ]
    lines = [
        f"recording {res['recording']}: {res['frames']} frames, {res['touched_frames']} touched "
        f"(wrench force minus bias above {res['force_threshold_n']} N; "
        f"the first {res['reference_frames']} frames are the reference and are not scored)",
        "",
        "| estimator | " + " | ".join(c[0] for c in cols) + " |",
        "|" + "---|" * (len(cols) + 1),
    ]
    for name, st in res["estimators"].items():
        cells = [_fmt(st[k], 2) if st[k] is not None else "-" for _, k in cols]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
