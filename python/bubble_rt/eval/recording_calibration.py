"""Calibration of E, k_f, k_u on recordings that carry a force/torque wrench.

The loss is the paper's (:mod:`bubble_rt.eval.calibration`) with the
recorded wrench standing in for the simulator's net force::

    L = sum_i lambda1 * ||f_net_i - R (w_i - b)||_2  +  lambda2 * sum_{i with contact truth}
        (1/N) sum_n |C_n - c_gt_n|

* ``w_i`` is frame i's recorded force (the first three wrench components, N) in the
  force/torque sensor's own frame; ``b`` the wrench bias of its recording: the mean wrench
  force over the recording's untouched reference frames (the frames the estimator captures
  its reference from);
* ``R`` (3 x 3) maps F/T-frame vectors into the sensor's mesh frame. Either given (the
  ``[wrench] rotation`` of a ``--wrench-config`` file, any orthonormal matrix) or fitted
  jointly: inside every loss evaluation, after the estimates, the proper rotation that best
  aligns the bias-free wrenches onto the estimated net forces (least squares, Kabsch) is
  used, so the optimiser sees the loss at the best rotation for those parameters. One
  rotation for all recordings (one sensor on one mount). A fitted rotation is proper; an F/T
  sensor reporting the opposite sign (the reaction) is declared with ``[wrench] sign = -1``,
  which negates ``w - b`` first (a given rotation may be improper and absorb the sign itself);
* the contact term counts only frames with contact truth (simulated frames passed in memory,
  whose ``Frame.truth`` gives it on the mesh's nodes); real recordings have none and are
  scored on the force term alone.

The rest tension governs the force a dent means, and it follows from the rest gauge pressure,
which a sensor reading absolute pressure cannot know: so the ambient pressure is fitted too, as
``gauge_pa`` (the first recording's rest gauge pressure, log-scaled like the others) and written
out as ``ambient_pa`` (the first recording's reference pressure minus it; one ambient for all
recordings). Every estimator is linearised about its own recording's reference pressure.

The torque is read but not used. Per recording the mesh is fitted on its own reference
frames, and (U, dp) are tracked once per frame (they do not depend on E, k_f, k_u), so one
loss evaluation is only solves, fanned out like :class:`~bubble_rt.eval.calibration.
CalibrationProblem`'s. The optimiser is :func:`bubble_rt.eval.calibration.calibrate` and the
output the same TOML (:func:`~bubble_rt.eval.calibration.write_config`).

Recordings are opened with :func:`bubble_rt.io.recordings.open_recording` only (Punyo .npy
with ``data.json`` wrenches, the project's MCAP files with their ``/bubble_rt/wrench``
channel, and any layout added behind it). A recording with separate reference frames (MCAP)
uses them; otherwise its first ``n_reference`` frames are the reference and not scored.
"""

from __future__ import annotations

import time
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.estimation.estimator import ABSOLUTE_PRESSURE_MIN, EstimatorConfig
from bubble_rt.eval import FanOut
from bubble_rt.eval.calibration import (
    DEFAULTS,
    PARAMS,
    CalibrationResult,
    LossWeights,
    _sigmoid,
    calibrate,
    contact_threshold,
    fem_factory,
    worker_estimator,
)

#: What ``calibrate --recording`` fits, all of them by default: the paper's three and the
#: ambient pressure, which sets the rest tension (the F/T rotation too, unless given).
FIT_PARAMS = (*PARAMS, "ambient_pa")


class WrenchCalibrationError(ValueError):
    """A recording or wrench configuration cannot be used; the text names the file or key."""


@dataclass
class WrenchFrame:
    """One observation: displacement U (N x 3, m), dp (Pa), the bias-free recorded force ``w``
    (3,) N in the F/T frame, and contact truth (N,) bool where the frame has any."""

    U: NDArray[np.float64]
    dp: float
    w: NDArray[np.float64]
    c_gt: NDArray[np.bool_] | None = None
    index: int = 0


@dataclass
class RecordingSet:
    """The tracked frames of one recording on its own fitted mesh."""

    name: str
    mesh: Any
    frames: list[WrenchFrame]
    bias: NDArray[np.float64]  # (6,) mean wrench of the reference frames
    n_reference: int
    reference_pressure_pa: float | None = None  # the reference's reading (Pa)


def fem_at_reference(
    reference_pressure_pa: float | None, mesh: Any, params: dict[str, float]
) -> Any:
    """The FEM estimator for ``params`` linearised about a recording's reference pressure
    (``functools.partial`` it with the pressure: a picklable factory)."""
    from types import SimpleNamespace

    from bubble_rt.estimation.registry import make_estimator
    from bubble_rt.eval import estimator_config

    reference = SimpleNamespace(pressure_pa=reference_pressure_pa)
    return make_estimator("fem", mesh, estimator_config(params), reference=reference)


# ------------------------------------------------------------------------------ rotation
def kabsch(source: NDArray[np.float64], target: NDArray[np.float64]) -> NDArray[np.float64]:
    """The proper rotation R minimising sum_i ||target_i - R source_i||^2 (K x 3 each)."""
    P = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    Q = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    U, _, Vt = np.linalg.svd(P.T @ Q)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    return np.asarray(Vt.T @ np.diag([1.0, 1.0, d]) @ U.T)


def rotation_angle_deg(A: NDArray[np.float64], B: NDArray[np.float64]) -> float:
    """Angle (degrees) of the rotation A B^T between two rotations."""
    c = (np.trace(np.asarray(A) @ np.asarray(B).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def check_rotation(R: Any, where: str = "rotation") -> NDArray[np.float64]:
    """A 3 x 3 orthonormal matrix (rows), or WrenchCalibrationError naming ``where``."""
    try:
        M = np.asarray(R, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise WrenchCalibrationError(f"{where}: not a 3 x 3 matrix of numbers ({exc})") from exc
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise WrenchCalibrationError(f"{where}: must be 3 x 3 finite numbers, got {M.shape}")
    if not np.allclose(M @ M.T, np.eye(3), atol=1e-4):
        raise WrenchCalibrationError(f"{where}: not orthonormal (R R^T != I within 1e-4)")
    return M


def load_wrench_config(path: str | Path) -> dict[str, Any]:
    """Read a wrench configuration TOML: a ``[wrench]`` table with the optional keys
    ``rotation`` (3 x 3 rows, F/T frame -> mesh frame; absent: fitted), ``sign`` (1 or -1:
    -1 when the F/T sensor reports the reaction) and ``reference_frames`` (int). Unknown keys
    or tables are errors naming the key."""
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text())
    except FileNotFoundError as exc:
        raise WrenchCalibrationError(f"{p}: no such wrench configuration") from exc
    except tomllib.TOMLDecodeError as exc:
        raise WrenchCalibrationError(f"{p}: not valid TOML ({exc})") from exc
    extra = set(doc) - {"wrench"}
    if extra:
        raise WrenchCalibrationError(f"{p}: unknown table(s) {sorted(extra)} (only [wrench])")
    table = doc.get("wrench", {})
    out: dict[str, Any] = {}
    for key, val in table.items():
        if key == "rotation":
            out["rotation"] = check_rotation(val, f"{p}: wrench.rotation")
        elif key == "reference_frames":
            if not isinstance(val, int) or val < 1:
                raise WrenchCalibrationError(f"{p}: wrench.reference_frames must be an int >= 1")
            out["reference_frames"] = val
        elif key == "sign":
            if val not in (1, -1) or isinstance(val, bool):
                raise WrenchCalibrationError(f"{p}: wrench.sign must be 1 or -1, got {val!r}")
            out["sign"] = float(val)
        else:
            raise WrenchCalibrationError(
                f"{p}: unknown key wrench.{key} (known: rotation, sign, reference_frames)"
            )
    return out


# ------------------------------------------------------------------------------ loading
def _track(
    name: str,
    reference_frames: Sequence[Any],
    frames: Sequence[Any],
    camera: Any,
    *,
    mesh: str = "medium",
    flow: str = "default",
) -> RecordingSet:
    """Fit the mesh on the reference frames, remove the wrench bias, track every frame."""
    from bubble_rt.estimation.deformation import DeformationTracker, FlowSettings, Reference
    from bubble_rt.estimation.fitting import fit_mesh
    from bubble_rt.mesh import Mesh

    if not reference_frames:
        raise WrenchCalibrationError(f"{name}: no reference (untouched) frames")
    if not frames:
        raise WrenchCalibrationError(f"{name}: no frame to calibrate on after the reference")
    for kind, seq in (("reference frame", reference_frames), ("frame", frames)):
        for k, f in enumerate(seq):
            if f.wrench is None:
                raise WrenchCalibrationError(
                    f"{name}: {kind} {getattr(f, 'index', k)} has no wrench (calibration on "
                    "recordings needs a force/torque reading on every frame)"
                )
    bias = np.mean([np.asarray(f.wrench, dtype=np.float64) for f in reference_frames], axis=0)
    reference = Reference.capture(list(reference_frames))
    template = Mesh.preset(mesh) if not str(mesh).isdigit() else Mesh.generate(int(mesh))
    fitted = fit_mesh(template, reference, camera)
    settings = FlowSettings() if flow == "default" else FlowSettings(method=flow)
    tracker = DeformationTracker(fitted, camera, reference, settings)
    out = []
    for f in frames:
        d = tracker.track(f)
        truth = getattr(f, "truth", None)
        c_gt = None
        if truth is not None and hasattr(truth, "contact_mask"):
            if not getattr(truth, "converged", True):
                continue  # the simulator flags this truth as unreliable: no observation
            c_gt = np.asarray(truth.contact_mask(fitted), dtype=bool)
        out.append(
            WrenchFrame(
                U=np.asarray(d.U, dtype=np.float64),
                dp=float(d.dp),
                w=np.asarray(f.wrench, dtype=np.float64)[:3] - bias[:3],
                c_gt=c_gt,
                index=int(getattr(f, "index", 0)),
            )
        )
    return RecordingSet(
        name, fitted, out, bias, len(reference_frames), reference_pressure_pa=reference.pressure_pa
    )


def frames_set(
    name: str,
    reference_frames: Sequence[Any],
    frames: Sequence[Any],
    camera: Any,
    *,
    mesh: str = "medium",
    flow: str = "default",
) -> RecordingSet:
    """A set from frames in memory (e.g. simulated ones carrying a wrench, and their truth)."""
    return _track(name, reference_frames, frames, camera, mesh=mesh, flow=flow)


def load_recording(
    path: str | Path,
    *,
    mesh: str = "medium",
    n_reference: int = 5,
    flow: str = "default",
    pose: NDArray[np.float64] | None = None,
    centre_from_data: bool = True,
    max_frames: int = 0,
) -> RecordingSet:
    """Open a recording (:func:`bubble_rt.io.recordings.open_recording`) and track it.

    ``n_reference``: reference frames (the recording's own reference frames when it has them,
    else its first frames, which are then not scored); ``pose`` / ``centre_from_data`` go to
    ``open_recording``; ``max_frames`` caps the scored frames (0: all).
    """
    from bubble_rt.io.recordings import open_recording

    try:
        rec: Any = open_recording(path, pose=pose, centre_from_data=centre_from_data)
    except (FileNotFoundError, ValueError) as exc:
        raise WrenchCalibrationError(f"{path}: {exc}") from exc
    if getattr(rec, "has_reference", False):
        ref = list(rec.reference_frames(n_reference))
        frames = list(rec)
    else:
        allf = list(rec)
        if len(allf) <= n_reference:
            raise WrenchCalibrationError(
                f"{path}: {len(allf)} frames, but the first {n_reference} are the reference"
            )
        ref, frames = allf[:n_reference], allf[n_reference:]
    if max_frames:
        frames = frames[:max_frames]
    return _track(Path(path).name, ref, frames, rec.camera, mesh=mesh, flow=flow)


# ------------------------------------------------------------------------------ problem
@dataclass
class OutputTask:
    """A chunk of one recording's frames and the parameters to estimate them with."""

    token: str
    mesh: Any
    frames: list[WrenchFrame]
    params: dict[str, float]
    factory: Callable[[Any, dict[str, float]], Any] = fem_factory
    weights: LossWeights = LossWeights()
    k_const: float = 2000.0
    k_linear: float = 2.0


def chunk_outputs(task: OutputTask) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(net forces K x 3, contact terms K; NaN where no contact truth) of one chunk."""
    est = worker_estimator(task.token, task.mesh, task.params, task.factory)
    areas = task.mesh.lumped_areas()
    forces = np.zeros((len(task.frames), 3))
    contact = np.full(len(task.frames), np.nan)
    for k, fr in enumerate(task.frames):
        e = est.estimate(fr.U, fr.dp)
        forces[k] = np.asarray(e.net_force, dtype=np.float64)
        if fr.c_gt is not None:
            p = np.asarray(e.normal_pressure, dtype=np.float64)
            thresh = contact_threshold(p, areas, task.k_const, task.k_linear)
            c = _sigmoid(task.weights.k_opt * (p - thresh) / thresh)
            contact[k] = float(np.mean(np.abs(c - fr.c_gt.astype(np.float64))))
    return forces, contact


@dataclass
class Evaluation:
    """One loss evaluation: the loss, its two terms, the rotation used, per-frame forces."""

    loss: float
    force_term: float
    contact_term: float
    rotation: NDArray[np.float64]
    net_forces: NDArray[np.float64]  # K x 3, mesh frame
    wrenches: NDArray[np.float64]  # K x 3, bias-free, F/T frame


@dataclass
class RecordingProblem:
    """Tracked recordings and the summed loss against their wrenches.

    ``rotation``: F/T frame -> mesh frame, or None to fit it (Kabsch) in every evaluation;
    ``sign``: -1 negates the bias-free wrenches first (an F/T sensor reporting the reaction).
    """

    sets: list[RecordingSet]
    rotation: NDArray[np.float64] | None = None
    sign: float = 1.0
    factory: Callable[[Any, dict[str, float]], Any] = fem_factory
    weights: LossWeights = LossWeights()
    k_const: float = 2000.0
    k_linear: float = 2.0
    token: str = field(default_factory=lambda: f"reccalib-{time.time_ns()}")

    @property
    def frames(self) -> list[WrenchFrame]:
        return [f for s in self.sets for f in s.frames]

    @property
    def contact_frames(self) -> int:
        return sum(f.c_gt is not None for f in self.frames)

    @property
    def rest_pressure_pa(self) -> float | None:
        """The first recording's reference pressure (Pa), which ``gauge_pa`` is relative to."""
        return self.sets[0].reference_pressure_pa if self.sets else None

    def estimator_params(self, params: dict[str, float]) -> dict[str, float]:
        """Estimator parameters from the fitted ones: ``gauge_pa`` becomes ``ambient_pa``."""
        out = {k: v for k, v in params.items() if k != "gauge_pa"}
        if "gauge_pa" in params and self.rest_pressure_pa is not None:
            out["ambient_pa"] = float(self.rest_pressure_pa) - params["gauge_pa"]
        return out

    def tasks(self, n: int, params: dict[str, float]) -> list[OutputTask]:
        """Chunks of every set, ``n`` in all at most (at least one per set)."""
        params = self.estimator_params(params)
        total = max(1, len(self.frames))
        out = []
        for si, s in enumerate(self.sets):
            k = max(1, min(len(s.frames), round(n * len(s.frames) / total)))
            for ci, idx in enumerate(np.array_split(np.arange(len(s.frames)), k)):
                out.append(
                    OutputTask(
                        token=f"{self.token}-{si}-{ci}",
                        mesh=s.mesh,
                        frames=[s.frames[i] for i in idx],
                        params=dict(params),
                        factory=(
                            partial(fem_at_reference, s.reference_pressure_pa)
                            if self.factory is fem_factory
                            else self.factory
                        ),
                        weights=self.weights,
                        k_const=self.k_const,
                        k_linear=self.k_linear,
                    )
                )
        return out

    def evaluate(self, params: dict[str, float], fan: FanOut | None = None) -> Evaluation:
        fan = fan or FanOut(1)
        parts = fan.map(chunk_outputs, self.tasks(fan.parallelism, params))
        F = np.vstack([p[0] for p in parts]) if parts else np.zeros((0, 3))
        C = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
        W = self.sign * np.array([f.w for f in self.frames]).reshape(-1, 3)
        R = self.rotation if self.rotation is not None else kabsch(W, F)
        force = float(np.linalg.norm(F - W @ R.T, axis=1).sum())
        contact = float(np.nansum(C)) if np.any(np.isfinite(C)) else 0.0
        loss = self.weights.lambda1 * force + self.weights.lambda2 * contact
        return Evaluation(loss, force, contact, np.asarray(R), F, W)

    def loss(self, params: dict[str, float], fan: FanOut | None = None) -> float:
        """Summed loss over all frames of all recordings for these parameters."""
        return self.evaluate(params, fan).loss


@dataclass
class RecordingCalibration:
    """The calibration (:class:`CalibrationResult`) plus what the wrench side found."""

    result: CalibrationResult
    rotation: NDArray[np.float64]
    rotation_fitted: bool
    #: Singular values of the wrench directions' scatter, largest first: a rotation fitted
    #: from wrenches that all point one way leaves the spin about that axis undetermined
    #: (the ratio of the second to the first tells; near 0 = poorly determined).
    wrench_spread: NDArray[np.float64]
    biases: dict[str, list[float]]
    final: Evaluation

    def info(self) -> dict[str, Any]:
        """Provenance for the TOML header comments."""
        return {
            "rotation_ft_to_mesh": np.round(self.rotation, 6).tolist(),
            "rotation_fitted": self.rotation_fitted,
            "wrench_spread": np.round(self.wrench_spread, 6).tolist(),
            "wrench_bias": {k: [round(x, 6) for x in v] for k, v in self.biases.items()},
            "force_term": round(self.final.force_term, 6),
            "contact_term": round(self.final.contact_term, 6),
        }


def wrench_spread(W: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalised singular values of the wrench force scatter (3,), largest first."""
    W = np.asarray(W, dtype=np.float64).reshape(-1, 3)
    if not len(W):
        return np.zeros(3)
    s = np.linalg.svd(W, compute_uv=False)
    s = np.pad(np.asarray(s, dtype=np.float64), (0, 3 - len(s)))
    return np.asarray(s / s[0] if s[0] > 0 else s, dtype=np.float64)


def calibrate_recordings(
    problem: RecordingProblem,
    *,
    initial: dict[str, float] | None = None,
    method: str = "Nelder-Mead",
    max_evals: int = 60,
    bound: float = 10.0,
    step: float = 0.5,
    fan: FanOut | None = None,
    progress: bool = False,
    fit: Sequence[str] = FIT_PARAMS,
) -> RecordingCalibration:
    """Minimise the recording loss over the logarithms of the ``fit`` parameters (of
    :data:`FIT_PARAMS`; as :func:`calibrate`), the others held at ``initial`` (default: the
    estimator's values), then report the rotation at the best parameters. ``ambient_pa`` is
    searched as the rest gauge pressure ``gauge_pa`` (it needs recordings that read absolute
    pressure); the result's params name ``ambient_pa``."""
    bad = [k for k in fit if k not in FIT_PARAMS]
    if bad or not fit:
        raise WrenchCalibrationError(
            f"cannot fit {bad or 'nothing'}: choose among {', '.join(FIT_PARAMS)}"
        )
    own_fan = fan is None
    fan = fan or FanOut(1)
    start = {**DEFAULTS, "ambient_pa": EstimatorConfig().ambient_pa, **(initial or {})}
    rest = problem.rest_pressure_pa
    if "ambient_pa" in fit:
        if rest is None or rest <= ABSOLUTE_PRESSURE_MIN:
            raise WrenchCalibrationError(
                "ambient_pa: the recordings' pressure is not absolute, so there is no ambient "
                "pressure to fit"
            )
    start["gauge_pa"] = float(rest) - start.pop("ambient_pa") if rest is not None else 0.0
    names = tuple("gauge_pa" if k == "ambient_pa" else k for k in fit)
    try:
        res = calibrate(
            problem,
            params=names,
            initial=start,
            method=method,
            max_evals=max_evals,
            bound=bound,
            step=step,
            fan=fan,
            progress=progress,
        )
        final = problem.evaluate(res.params, fan)
    finally:
        if own_fan:
            fan.close()
    res = replace(
        res,
        params=problem.estimator_params(res.params),
        initial_params=problem.estimator_params(res.initial_params),
    )
    return RecordingCalibration(
        result=res,
        rotation=final.rotation,
        rotation_fitted=problem.rotation is None,
        wrench_spread=wrench_spread(final.wrenches),
        biases={s.name: [float(x) for x in s.bias] for s in problem.sets},
        final=final,
    )
