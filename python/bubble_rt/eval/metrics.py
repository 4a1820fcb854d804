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
- Light-touch detection rate: among frames whose true net force is within
  :data:`LIGHT_TOUCH_RANGE_N` (0.1-1.5 N), the fraction where the estimate marks at least one
  contact node. The truth's node mask does not enter: an indenter pressing between estimator
  nodes leaves it empty, yet the touch is there to detect.
- False contacts: among untouched frames (true net force below :data:`UNTOUCHED_N`, 0.05 N),
  the fraction where the estimate marks any contact node; ``false_nodes`` is the mean number of
  contact nodes on those frames. ``n_light`` / ``n_untouched`` count the frames each rate is
  over (a rate over no frame is NaN).

Force errors are averaged over all frames of a trajectory (untouched ones included), as the
paper's table does; ``force_err_contact_n`` averages over touched frames only (true net force
at least :data:`UNTOUCHED_N`).

Wrench and patch geometry (frames whose true net force is at least :data:`WRENCH_MIN_N`, 1 N):

- Torque: ``|tau - tau_gt| / |tau_gt|``, tau the estimate's net torque about the mesh origin
  (``bubble_rt.wrench``: its forces at its displaced nodes, as the daemon publishes it),
  tau_gt the simulator's (its contact forces at the nodes' current positions, the physical
  torque); the median over frames is reported (``torque_rel_err``).
  ``torque_rel_err_reference`` compares with the truth's forces at their untouched positions
  instead, which shows how much the dent's motion moves the torque.
  ``torque_lever_err_mm``: the median of ``|tau - tau_gt| / |f_gt|`` (mm), the torque error as
  a point-of-action error; it stays meaningful where the true torque is small (a press near
  the dome's axis), which inflates the relative error.
- Patch centroid: each true patch carrying at least :data:`PATCH_MIN_N` is matched (largest
  first) to the nearest unmatched estimated patch; the distance from the truth's force-weighted
  centroid to the patch's area-weighted ``centroid`` and to its ``pressure_centroid`` (mm), or
  NaN when no estimated patch is left (counted as missed). Medians over all scored true
  patches, and the share within :data:`CENTROID_TOL_MM`.
- Patch area: each matched patch's ``area`` over its true patch's (the lumped areas of the
  true contact nodes on the simulation's finer mesh, the same convention), median
  ``patch_area_ratio`` and median ``patch_area_rel_err`` ``|ratio - 1|`` over matched patches.
- Two contacts: frames whose truth has exactly two patches of at least :data:`PATCH_MIN_N`
  (the ``split`` indenter's two pins, both pressing); found when the estimate has exactly two
  patches, matched one to one, each patch force within :data:`PATCH_FORCE_TOL` of its true
  patch's force (``|F - F_gt| <= 0.2 |F_gt|``, vectors: ``two_contact_rate``; magnitudes,
  ``||F| - |F_gt|| <= 0.2 |F_gt|``: ``two_contact_magnitude_rate``).

Frames whose simulated ground truth did not converge (``truth.converged`` False: the physics
step failed even in substeps) are still run through the estimators, so warm starts see the
whole trajectory, but are left out of every statistic and counted in ``n_excluded``: a force
the simulator itself flags as unreliable is no ground truth.

"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.estimation.registry import estimator_kinds
from bubble_rt.mesh import lumped_areas as lumped_areas  # re-exported for evaluation code
from bubble_rt.mesh import vertex_normals as vertex_normals
from bubble_rt.sim.truth import TOUCH_N

#: True net force (N) below which a frame counts as untouched: the false-contact rate is over
#: these frames only (the truth's own definition of a touch, ``sim.truth.TOUCH_N``).
UNTOUCHED_N = TOUCH_N
#: Range (N, inclusive) of true net force of a light touch, whose detection rate is reported.
LIGHT_TOUCH_RANGE_N = (0.1, 1.5)
#: True net force (N) from which a frame's torque and patches are scored (the issue's 1 N).
WRENCH_MIN_N = 1.0
#: Force (N) a true patch must carry to be scored (a grazing second contact below it is a
#: light touch, not a patch to locate).
PATCH_MIN_N = 0.5
#: Patch centroid target (mm) and patch force tolerance (relative) of the two-contact score.
CENTROID_TOL_MM = 2.0
PATCH_FORCE_TOL = 0.2
GEOMETRIES = ("round", "point", "line", "square", "split")
#: The registered estimator kinds (all are evaluated unless a task names some).
ESTIMATORS = estimator_kinds()


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
    #: estimated contact nodes outside the truth's node mask
    false_nodes: int
    time_ms: float = float("nan")
    truth_converged: bool = True
    #: net torque (3,) N m, estimate and truth (empty when not computed)
    tau_est: list[float] = field(default_factory=list)
    tau_gt: list[float] = field(default_factory=list)
    tau_gt_reference: list[float] = field(default_factory=list)
    #: per scored true patch: centroid errors (mm; NaN = no estimated patch matched)
    centroid_err_mm: list[float] = field(default_factory=list)
    pressure_centroid_err_mm: list[float] = field(default_factory=list)
    #: per matched true patch: estimated patch area / true patch area
    patch_area_ratio: list[float] = field(default_factory=list)
    #: the truth has two scored patches / the estimate found them (see the module docstring)
    two_contact: bool = False
    two_found: bool = False
    two_found_magnitude: bool = False
    est_patches: int = 0


@dataclass(frozen=True)
class PatchScore:
    """What :func:`patch_scores` measures on one frame."""

    centroid_err_mm: list[float]
    pressure_centroid_err_mm: list[float]
    area_ratio: list[float]
    two_contact: bool
    two_found: bool
    two_found_magnitude: bool


def patch_scores(est_patches: Sequence[Any], true_patches: Sequence[Any]) -> PatchScore:
    """Centroid errors and the two-contact score of one frame (module docstring).

    Args:
        est_patches: estimated patches (``centroid``, ``pressure_centroid``, ``force``; m, N).
        true_patches: true patches (``centroid``: force-weighted, m; ``force`` N; ``area``
            m^2, optional).
    """
    scored = [t for t in true_patches if float(np.linalg.norm(t.force)) >= PATCH_MIN_N]
    scored.sort(key=lambda t: -float(np.linalg.norm(t.force)))
    free = list(range(len(est_patches)))
    err_a: list[float] = []
    err_p: list[float] = []
    area: list[float] = []
    pairs: list[tuple[Any, Any]] = []
    for t in scored:
        c = np.asarray(t.centroid, dtype=np.float64)
        if not free:
            err_a.append(float("nan"))
            err_p.append(float("nan"))
            continue
        d = [float(np.linalg.norm(np.asarray(est_patches[k].centroid) - c)) for k in free]
        k = free.pop(int(np.argmin(d)))
        e = est_patches[k]
        pc = np.asarray(getattr(e, "pressure_centroid", e.centroid), dtype=np.float64)
        pc = pc if pc.size == 3 else np.asarray(e.centroid, dtype=np.float64)
        err_a.append(1e3 * min(d))
        err_p.append(1e3 * float(np.linalg.norm(pc - c)))
        true_area = float(getattr(t, "area", float("nan")))
        if true_area > 0:
            area.append(float(getattr(e, "area", float("nan"))) / true_area)
        pairs.append((e, t))
    two = len(scored) == 2 and len(est_patches) == 2 and len(pairs) == 2

    def close(e: Any, t: Any, magnitude: bool) -> bool:
        fe, ft = np.asarray(e.force, dtype=np.float64), np.asarray(t.force, dtype=np.float64)
        n = float(np.linalg.norm(ft))
        err = abs(float(np.linalg.norm(fe)) - n) if magnitude else float(np.linalg.norm(fe - ft))
        return err <= PATCH_FORCE_TOL * n

    found = two and all(close(e, t, False) for e, t in pairs)
    found_mag = two and all(close(e, t, True) for e, t in pairs)
    return PatchScore(err_a, err_p, area, len(scored) == 2, bool(found), bool(found_mag))


def relative_error(est: Sequence[float] | NDArray, truth: Sequence[float] | NDArray) -> float:
    """``|est - truth| / |truth|`` (NaN when the truth is zero or either is missing)."""
    e = np.asarray(est, dtype=np.float64)
    g = np.asarray(truth, dtype=np.float64)
    if e.size != 3 or g.size != 3:
        return float("nan")
    n = float(np.linalg.norm(g))
    return float(np.linalg.norm(e - g) / n) if n > 0 else float("nan")


def wrench_stats(records: Sequence[FrameMetrics]) -> dict[str, float]:
    """Torque, centroid and two-contact statistics over converged frames of at least
    :data:`WRENCH_MIN_N` (module docstring); NaN where a class has no frame."""
    recs = [r for r in records if r.truth_converged and true_force(r) >= WRENCH_MIN_N]
    tau = [relative_error(r.tau_est, r.tau_gt) for r in recs]
    tau = [x for x in tau if not math.isnan(x)]
    tau_ref = [relative_error(r.tau_est, r.tau_gt_reference) for r in recs]
    lever = [
        1e3 * float(np.linalg.norm(np.subtract(r.tau_est, r.tau_gt))) / true_force(r)
        for r in recs
        if len(r.tau_est) == 3 and len(r.tau_gt) == 3
    ]
    ca = [x for r in recs for x in r.centroid_err_mm]
    cp = [x for r in recs for x in r.pressure_centroid_err_mm]
    two = [r for r in recs if r.two_contact]
    area = [x for r in recs for x in r.patch_area_ratio]

    def med(v: list[float]) -> float:
        v = [x for x in v if not math.isnan(x)]
        return float(np.median(v)) if v else float("nan")

    def within(v: list[float]) -> float:
        # a missed patch (NaN) counts as not within
        return sum(1 for x in v if x <= CENTROID_TOL_MM) / len(v) if v else float("nan")

    return {
        "torque_rel_err": med(tau),
        "torque_rel_err_reference": med(tau_ref),
        "torque_lever_err_mm": med(lever),
        "centroid_err_mm": med(ca),
        "pressure_centroid_err_mm": med(cp),
        "centroid_within_tol": within(ca),
        "pressure_centroid_within_tol": within(cp),
        "patch_area_ratio": med(area),
        "patch_area_rel_err": med([abs(x - 1.0) for x in area]),
        "two_contact_rate": (sum(r.two_found for r in two) / len(two) if two else float("nan")),
        "two_contact_magnitude_rate": (
            sum(r.two_found_magnitude for r in two) / len(two) if two else float("nan")
        ),
        "n_wrench": float(len(recs)),
        "n_torque": float(len(tau)),
        "n_patches_scored": float(len(ca)),
        "n_patches_missed": float(sum(math.isnan(x) for x in ca)),
        "n_two_contact": float(len(two)),
    }


WRENCH_KEYS = (
    "torque_rel_err",
    "torque_rel_err_reference",
    "torque_lever_err_mm",
    "centroid_err_mm",
    "pressure_centroid_err_mm",
    "centroid_within_tol",
    "pressure_centroid_within_tol",
    "patch_area_ratio",
    "patch_area_rel_err",
    "two_contact_rate",
    "two_contact_magnitude_rate",
    "n_wrench",
    "n_torque",
    "n_patches_scored",
    "n_patches_missed",
    "n_two_contact",
)


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


def true_force(record: FrameMetrics) -> float:
    """|f_gt| (N) of a frame record."""
    return float(np.linalg.norm(record.f_gt))


def thresholds() -> dict[str, Any]:
    """The force thresholds the frame classes use (N), as reported in tables and JSON."""
    return {"untouched_below_n": UNTOUCHED_N, "light_touch_n": list(LIGHT_TOUCH_RANGE_N)}


def wrench_thresholds() -> dict[str, float]:
    """The bounds the wrench and patch scores use, as reported in JSON."""
    return {
        "wrench_min_n": WRENCH_MIN_N,
        "patch_min_n": PATCH_MIN_N,
        "centroid_tol_mm": CENTROID_TOL_MM,
        "patch_force_tol": PATCH_FORCE_TOL,
    }


def aggregate(records: Sequence[FrameMetrics]) -> dict[str, float]:
    """Summary statistics of a group of frame records (see the module docstring)."""
    recs = [r for r in records if r.truth_converged]
    n_excluded = len(records) - len(recs)
    lo, hi = LIGHT_TOUCH_RANGE_N
    light = [r for r in recs if lo <= true_force(r) <= hi]
    untouched = [r for r in recs if true_force(r) < UNTOUCHED_N]
    contact = [r for r in recs if true_force(r) >= UNTOUCHED_N]
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
        "false_nodes": _nanmean(float(r.est_nodes) for r in untouched),
        "time_ms": _nanmean(r.time_ms for r in recs),
        "n_frames": float(len(recs)),
        "n_light": float(len(light)),
        "n_untouched": float(len(untouched)),
        "n_excluded": float(n_excluded),
        **wrench_stats(records),
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


#: Statistics over a class of frames, and the count of that class: the average pools them.
_POOLED = {
    "light_touch_rate": "n_light",
    "false_contact_rate": "n_untouched",
    "false_nodes": "n_untouched",
}


def _pooled(per: Sequence[dict[str, float]], key: str, n: str) -> float:
    """``key`` over the union of the groups' frames of class ``n`` (NaN when there are none)."""
    total = sum(p[n] for p in per)
    if not total:
        return float("nan")
    return float(sum(p[key] * p[n] for p in per if p[n]) / total)


def summarize(records: Sequence[FrameMetrics]) -> dict[str, Any]:
    """``{"geometries": {g: {est: stats}}, "average": {est: stats}, "thresholds": {...}}``
    (``thresholds``: :func:`thresholds`, the force bounds of the untouched and light-touch
    frames).

    The average is the unweighted mean over geometries of each statistic (as the paper's table),
    ignoring geometries where a statistic is undefined; except the light-touch and
    false-contact statistics, which pool the frames of their class over geometries (the share
    of all light-touch / untouched frames), and the frame counts, which are summed.
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
        for key in ("n_frames", "n_excluded", "n_light", "n_untouched"):
            stats[key] = float(sum(p[key] for p in per))
        # Rates over a class of frames are pooled: the share of all such frames.
        for key, n in _POOLED.items():
            stats[key] = _pooled(per, key, n)
        # Medians and shares of the wrench scores: over all frames of every indenter.
        stats.update(wrench_stats([r for r in records if r.estimator == e]))
        average[e] = stats
    return {
        "geometries": geoms,
        "average": average,
        "thresholds": thresholds(),
        "wrench_thresholds": wrench_thresholds(),
    }
