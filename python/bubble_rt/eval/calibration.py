"""Calibration of E, k_f and k_u with the paper's loss (docs/evaluation.md, `bubble-rt calibrate`).

Per observation (frame) with ground-truth net force ``f_gt`` (N) and node contact ``c_gt``::

    L = lambda1 * ||f_net - f_gt||_2 + lambda2 * (1/N) * sum_i |C_i - c_gt_i|
    C_i = sigmoid(k_opt * (p_i - thresh) / thresh)

``p_i`` is the estimator's normal pressure (Pa, inward positive) and ``thresh`` the contact
threshold the estimator itself uses, ``max(k_const, k_linear * (a . p) / sum(a))``.
lambda1 = 1 N^-1, lambda2 = 10, k_opt = 2. The sum of L over all frames is minimised by a SciPy
black-box optimiser (Nelder-Mead, or Powell) over ``x = log(theta / theta_default)`` for
``theta = (E, k_f, k_u)``, bounded to a factor ``bound`` either side of the defaults and to
``max_evals`` loss evaluations.

The per-frame displacements (U, dp) are computed once (flow + lifting are independent of the
three parameters) and cached, so one loss evaluation is only solves. Frames are split into
chunks evaluated in parallel (:class:`bubble_rt.eval.FanOut`); each worker keeps its
estimator across evaluations (a change of E rebuilds K, k_f / k_u are a cheap reconfigure).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from bubble_rt.estimation.estimator import EstimatorConfig
from bubble_rt.eval import CALIB_SEED_BASE, FanOut

PARAMS = ("E", "k_f", "k_u")
#: The estimator's defaults (EstimatorConfig), where the search starts.
DEFAULTS: dict[str, float] = {
    "E": EstimatorConfig().material.E,
    "k_f": EstimatorConfig().k_f,
    "k_u": EstimatorConfig().k_u,
}


@dataclass(frozen=True)
class LossWeights:
    """The paper's loss constants: lambda1 (N^-1), lambda2, k_opt."""

    lambda1: float = 1.0
    lambda2: float = 10.0
    k_opt: float = 2.0


@dataclass
class CalibFrame:
    """One cached observation: displacement U (N x 3, m), dp (Pa), f_gt (3,) N, c_gt (N,) bool."""

    U: NDArray[np.float64]
    dp: float
    f_gt: NDArray[np.float64]
    c_gt: NDArray[np.bool_]


def _sigmoid(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def contact_threshold(
    normal_pressure: NDArray[np.float64],
    areas: NDArray[np.float64],
    k_const: float,
    k_linear: float,
) -> float:
    """The estimator's contact threshold (Pa): max(k_const, k_linear * area-weighted mean p)."""
    p = np.asarray(normal_pressure, dtype=float)
    a = np.asarray(areas, dtype=float)
    return max(float(k_const), float(k_linear) * float(a @ p) / float(a.sum()))


def frame_loss(
    net_force: NDArray[np.float64],
    normal_pressure: NDArray[np.float64],
    areas: NDArray[np.float64],
    f_gt: NDArray[np.float64],
    c_gt: NDArray[np.bool_],
    *,
    k_const: float = 2000.0,
    k_linear: float = 2.0,
    weights: LossWeights = LossWeights(),
) -> float:
    """The paper's per-observation loss (dimensionless after lambda1 = 1 N^-1)."""
    p = np.asarray(normal_pressure, dtype=float)
    thresh = contact_threshold(p, areas, k_const, k_linear)
    c = _sigmoid(weights.k_opt * (p - thresh) / thresh)
    force_term = float(np.linalg.norm(np.asarray(net_force, float) - np.asarray(f_gt, float)))
    contact_term = float(np.mean(np.abs(c - np.asarray(c_gt, dtype=float))))
    return weights.lambda1 * force_term + weights.lambda2 * contact_term


# ------------------------------------------------------------------------- estimator factories
def fem_factory(mesh: Any, params: dict[str, float]) -> Any:
    """The product's FEM estimator for these parameters (E in Pa, k_f, k_u)."""
    from bubble_rt.estimation.registry import make_estimator
    from bubble_rt.eval import estimator_config

    return make_estimator("fem", mesh, estimator_config(params))


def _reconfigure(est: Any, params: dict[str, float]) -> bool:
    """Cheap k_f / k_u update in place; False when the estimator cannot do it."""
    fn = getattr(est, "reconfigure", None)
    if fn is None:
        return False
    fn(k_f=params["k_f"], k_u=params["k_u"])
    return True


@dataclass
class ChunkTask:
    """A chunk of cached frames plus the parameters to evaluate them with (picklable)."""

    token: str
    mesh: Any
    frames: list[CalibFrame]
    params: dict[str, float]
    factory: Callable[[Any, dict[str, float]], Any] = fem_factory
    weights: LossWeights = LossWeights()
    k_const: float = 2000.0
    k_linear: float = 2.0


# Per-process estimator cache: token -> ((E, ambient), estimator). Lives in each worker across evaluations.
_WORKER_ESTIMATORS: dict[str, tuple[tuple[float, float | None], Any]] = {}


def worker_estimator(
    token: str, mesh: Any, params: dict[str, float], factory: Callable[[Any, dict[str, float]], Any]
) -> Any:
    """This worker's estimator for ``token`` at ``params``: kept between loss evaluations and
    reconfigured in place; rebuilt (``factory``) when E or the ambient pressure changes, since
    that refactors K. A kept one starts cold, so that a loss is a function of the parameters
    alone (warm-started from another evaluation's last frame it moved by up to 5 %)."""
    key = (params["E"], params.get("ambient_pa"))
    cached = _WORKER_ESTIMATORS.get(token)
    if cached is not None and cached[0] == key and _reconfigure(cached[1], params):
        solver = getattr(cached[1], "solver", None)
        if solver is not None and hasattr(solver, "cold_start"):
            solver.cold_start()
        return cached[1]
    est = factory(mesh, params)
    _WORKER_ESTIMATORS[token] = (key, est)
    return est


def chunk_loss(task: ChunkTask) -> list[float]:
    """Per-frame losses of one chunk (run in a worker)."""
    est = worker_estimator(task.token, task.mesh, task.params, task.factory)
    areas = task.mesh.lumped_areas()
    out = []
    for fr in task.frames:
        e = est.estimate(fr.U, fr.dp)
        out.append(
            frame_loss(
                e.net_force,
                e.normal_pressure,
                areas,
                fr.f_gt,
                fr.c_gt,
                k_const=task.k_const,
                k_linear=task.k_linear,
                weights=task.weights,
            )
        )
    return out


@dataclass
class CalibrationProblem:
    """Cached frames on one mesh and the machinery to evaluate the summed loss."""

    mesh: Any
    frames: list[CalibFrame]
    factory: Callable[[Any, dict[str, float]], Any] = fem_factory
    weights: LossWeights = LossWeights()
    k_const: float = 2000.0
    k_linear: float = 2.0
    token: str = field(default_factory=lambda: f"calib-{time.time_ns()}")

    def chunks(self, n: int, params: dict[str, float]) -> list[ChunkTask]:
        n = max(1, min(n, len(self.frames)))
        parts = np.array_split(np.arange(len(self.frames)), n)
        return [
            ChunkTask(
                token=f"{self.token}-{k}",
                mesh=self.mesh,
                frames=[self.frames[i] for i in idx],
                params=dict(params),
                factory=self.factory,
                weights=self.weights,
                k_const=self.k_const,
                k_linear=self.k_linear,
            )
            for k, idx in enumerate(parts)
        ]

    def loss(self, params: dict[str, float], fan: FanOut | None = None) -> float:
        """Summed loss over all frames for these parameters."""
        fan = fan or FanOut(1)
        parts = fan.map(chunk_loss, self.chunks(fan.parallelism, params))
        return float(sum(sum(p) for p in parts))


class LossProblem(Protocol):
    """What :func:`calibrate` minimises: :class:`CalibrationProblem`, or the recordings'
    :class:`bubble_rt.eval.recording_calibration.RecordingProblem`."""

    @property
    def frames(self) -> Sequence[Any]: ...

    def loss(self, params: dict[str, float], fan: FanOut | None = None) -> float: ...


@dataclass
class CalibrationResult:
    params: dict[str, float]
    loss: float
    initial_params: dict[str, float]
    initial_loss: float
    evaluations: int
    seconds: float
    n_frames: int
    history: list[tuple[dict[str, float], float]]

    @property
    def improvement(self) -> float:
        """Relative loss reduction from the initial parameters (0..1)."""
        return 1.0 - self.loss / self.initial_loss if self.initial_loss > 0 else 0.0


def calibrate(
    problem: LossProblem,
    *,
    params: Sequence[str] = PARAMS,
    initial: dict[str, float] | None = None,
    method: str = "Nelder-Mead",
    max_evals: int = 60,
    bound: float = 10.0,
    step: float = 0.5,
    fan: FanOut | None = None,
    progress: bool = False,
) -> CalibrationResult:
    """Minimise the summed loss over the logarithms of ``params`` (default E, k_f, k_u; each
    named in ``initial``, which defaults to the estimator's values).

    ``bound``: parameters stay within a factor ``bound`` of ``initial``; ``step``: initial
    simplex / direction size in log units; ``max_evals`` caps loss evaluations.
    """
    names = tuple(params)
    p0 = dict(DEFAULTS if initial is None else initial)
    own_fan = fan is None
    fan = fan or FanOut(1)
    history: list[tuple[dict[str, float], float]] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=max_evals, desc="calibrate", unit="eval")
    t0 = time.perf_counter()

    def params_of(x: NDArray[np.float64]) -> dict[str, float]:
        return {**p0, **{k: float(p0[k] * np.exp(x[i])) for i, k in enumerate(names)}}

    def objective(x: NDArray[np.float64]) -> float:
        prm = params_of(np.asarray(x, dtype=float))
        val = problem.loss(prm, fan)
        history.append((prm, val))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{val:.3f}", best=f"{min(h[1] for h in history):.3f}")
        return val

    try:
        x0 = np.zeros(len(names))
        f0 = objective(x0)
        _minimize(objective, x0, method, bound, step, max(1, max_evals - 1), f0)
    finally:
        if bar is not None:
            bar.close()
        if own_fan:
            fan.close()
    best_p, best_f = min(history, key=lambda h: h[1])
    return CalibrationResult(
        params=best_p,
        loss=best_f,
        initial_params=p0,
        initial_loss=f0,
        evaluations=len(history),
        seconds=time.perf_counter() - t0,
        n_frames=len(problem.frames),
        history=history,
    )


def _minimize(
    objective: Callable[[NDArray[np.float64]], float],
    x0: NDArray[np.float64],
    method: str,
    bound: float,
    step: float,
    budget: int,
    f0: float,
) -> None:
    """Run SciPy's Powell or Nelder-Mead on the log-parameters within +-log(bound), starting
    from a simplex / directions of size ``step``; the objective records every evaluation."""
    from scipy.optimize import minimize

    n = len(x0)
    bounds = [(-np.log(bound), np.log(bound))] * n
    if method.lower() == "powell":
        options: dict[str, Any] = {
            "maxfev": budget,
            "xtol": 1e-2,
            "ftol": 1e-4,
            "direc": step * np.eye(n),
        }
        minimize(objective, x0, method="Powell", bounds=bounds, options=options)
        return
    options = {
        "maxfev": budget,
        "initial_simplex": np.vstack([x0, x0 + step * np.eye(n)]),
        "xatol": 1e-2,
        "fatol": 1e-4 * max(1.0, abs(f0)),
    }
    minimize(objective, x0, method="Nelder-Mead", bounds=bounds, options=options)


# ------------------------------------------------------------------------- dataset / caching
@dataclass(frozen=True)
class CalibTrajectoryTask:
    """One calibration trajectory to simulate and track (picklable)."""

    geometry: str
    trajectory: int
    n_frames: int
    seed: int = CALIB_SEED_BASE
    mesh: str = "medium"
    flow_method: str = "default"
    n_reference: int = 5
    physics: Any = None  # simulator physics backend (None: the real one)


def default_trajectories(
    n_round: int = 5, n_point: int = 1, frames: int = 34, **kw: Any
) -> list[CalibTrajectoryTask]:
    """The paper's calibration set: five round-indenter trajectories and one point (~205 frames).

    The dataset's master seed is CALIB_SEED_BASE, disjoint from the evaluation's.
    """
    tasks = [CalibTrajectoryTask("round", k, frames, **kw) for k in range(n_round)]
    tasks += [CalibTrajectoryTask("point", k, frames, **kw) for k in range(n_point)]
    return tasks


def track_trajectory(task: CalibTrajectoryTask) -> tuple[Any, list[CalibFrame]]:
    """Simulate one trajectory and compute its (U, dp) per frame with the pipeline's first
    stage (flow + lifting)."""
    from bubble_rt.eval import build_pipeline, estimator_mesh, simulate_trajectory

    traj = simulate_trajectory(
        task.geometry,
        task.trajectory,
        task.n_frames,
        task.seed,
        n_reference=task.n_reference,
        render=task.flow_method != "oracle",
        physics=task.physics,
    )
    mesh = estimator_mesh(task.mesh, traj)
    pipeline = build_pipeline("fem", mesh, traj, None, task.flow_method)
    out = []
    for frame in traj.frames:
        d = pipeline.deform(frame)
        if not getattr(frame.truth, "converged", True):
            continue  # the simulator flags this ground truth as unreliable: no observation
        out.append(
            CalibFrame(
                U=np.asarray(d.U, dtype=float),
                dp=float(d.dp),
                f_gt=np.asarray(frame.truth.net_force, dtype=float),
                c_gt=np.asarray(frame.truth.contact_mask(mesh), dtype=bool),
            )
        )
    return mesh, out


def build_problem(
    tasks: Sequence[CalibTrajectoryTask],
    *,
    fan: FanOut | None = None,
    cache: str | Path | None = None,
    progress: bool = False,
) -> CalibrationProblem:
    """Track all calibration trajectories (in parallel) into a problem, cached in ``cache``.

    The cache (.npz) stores U, dp, f_gt, c_gt per frame and the mesh used; it is reused when it
    was made from the same task list.
    """
    from bubble_rt.mesh import Mesh

    key = repr(list(tasks))
    if cache and Path(cache).exists():
        z = np.load(cache, allow_pickle=False)
        if str(z["key"]) == key:
            mesh = Mesh(z["vertices"], z["triangles"], z["boundary"])
            frames = [
                CalibFrame(z["U"][i], float(z["dp"][i]), z["f_gt"][i], z["c_gt"][i])
                for i in range(len(z["dp"]))
            ]
            return CalibrationProblem(mesh, frames)
    fan = fan or FanOut(1)
    results = fan.map(track_trajectory, list(tasks), progress=progress, desc="track")
    # Every trajectory of one sim scene fits the same reference surface; keep the first mesh
    # (the fitted meshes differ by depth noise only, well below the displacements).
    mesh = results[0][0]
    frames = [f for _, fr in results for f in fr]
    if cache:
        Path(cache).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            cache,
            key=np.array(key),
            vertices=mesh.vertices,
            triangles=mesh.triangles,
            boundary=mesh.boundary,
            U=np.stack([f.U for f in frames]),
            dp=np.array([f.dp for f in frames]),
            f_gt=np.stack([f.f_gt for f in frames]),
            c_gt=np.stack([f.c_gt for f in frames]),
        )
    return CalibrationProblem(mesh, frames)


def write_config(
    path: str | Path, result: CalibrationResult, extra: dict[str, Any] | None = None
) -> None:
    """TOML the daemon and eval read: ``[estimator] k_f, k_u, youngs_modulus`` (Pa), and
    ``ambient_pa`` (Pa) when the calibration fitted it.

    The key for E is the daemon config's ``youngs_modulus`` (its loader rejects unknown keys
    and sections), so the provenance (losses, frames, settings) goes into comments.
    """
    import json

    import tomli_w

    doc = {
        "estimator": {
            "k_f": result.params["k_f"],
            "k_u": result.params["k_u"],
            "youngs_modulus": result.params["E"],
        }
    }
    if "ambient_pa" in result.params:
        doc["estimator"]["ambient_pa"] = result.params["ambient_pa"]
    info = {
        "loss_initial": round(result.initial_loss, 6),
        "loss": round(result.loss, 6),
        "improvement": round(result.improvement, 4),
        "frames": result.n_frames,
        "evaluations": result.evaluations,
        "seconds": round(result.seconds, 1),
        "initial": result.initial_params,
        **(extra or {}),
    }
    header = "# written by `bubble-rt calibrate` (paper loss, docs/evaluation.md)\n"
    header += "".join(f"# {k}: {json.dumps(v)}\n" for k, v in info.items())
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(header + tomli_w.dumps(doc))
