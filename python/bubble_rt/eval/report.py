"""Evaluation reports: markdown tables, JSON and figures."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.eval.metrics import (
    LIGHT_TOUCH_RANGE_N,
    UNTOUCHED_N,
    FrameMetrics,
    contact_iou,
    wrench_thresholds,
)
from bubble_rt.eval.tasks import TrajectoryResult


def _fmt(x: float, digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown_table(summary: dict[str, Any]) -> str:
    """The accuracy table: one row per geometry (and the average), columns per estimator, and
    the frame counts (all, light touches, untouched) the rates are over; a line under it
    states the force thresholds of those classes."""
    ests: list[str] = list(summary["average"].keys())
    lo, hi = LIGHT_TOUCH_RANGE_N
    cols = [
        ("mIoU", "miou", 3),
        ("force err (N)", "force_err_n", 2),
        ("normal err (N)", "normal_err_n", 2),
        ("shear err (N)", "shear_err_n", 2),
        (f"light det. ({lo:g}-{hi:g} N)", "light_touch_rate", 2),
        (f"false contact (< {UNTOUCHED_N:g} N)", "false_contact_rate", 2),
    ]
    header = ["geometry"] + [f"{e} {c[0]}" for e in ests for c in cols]
    header += ["frames", "light", "untouched"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    rows = list(summary["geometries"].items()) + [("average", summary["average"])]
    for name, per in rows:
        cells = [name]
        n, x, n_light, n_untouched = 0.0, 0.0, 0.0, 0.0
        for e in ests:
            st = per.get(e)
            for _, key, d in cols:
                cells.append(_fmt(st[key], d) if st else "-")
            if st:
                n = max(n, st["n_frames"])
                x = max(x, st.get("n_excluded", 0.0))
                n_light = max(n_light, st.get("n_light", 0.0))
                n_untouched = max(n_untouched, st.get("n_untouched", 0.0))
        cells.append(str(int(n)) + (f" (+{int(x)} excluded)" if x else ""))
        cells += [str(int(n_light)), str(int(n_untouched))]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append(
        f"\nlight: frames with true |f| in [{lo:g}, {hi:g}] N (the light-touch detection rate is "
        f"over them); untouched: true |f| < {UNTOUCHED_N:g} N (the false-contact rate is over "
        "them); average row: rates over those frames of every indenter"
    )
    lines.append("\n" + wrench_table(summary))
    return "\n".join(lines)


def wrench_table(summary: dict[str, Any]) -> str:
    """The wrench and patch scores (bubble_rt.eval.metrics' docstring): one row per geometry
    (and all frames), columns per estimator."""
    ests: list[str] = list(summary["average"].keys())
    th = summary.get("wrench_thresholds") or wrench_thresholds()
    tol = th["centroid_tol_mm"]
    cols = [
        ("torque err (median)", "torque_rel_err", 2),
        ("torque err vs untouched positions", "torque_rel_err_reference", 2),
        ("torque err / abs(f_gt) (mm)", "torque_lever_err_mm", 2),
        ("centroid err (mm)", "centroid_err_mm", 2),
        ("pressure centroid err (mm)", "pressure_centroid_err_mm", 2),
        (f"pressure centroid <= {tol:g} mm", "pressure_centroid_within_tol", 2),
        ("patch area / truth", "patch_area_ratio", 2),
        ("two contacts found", "two_contact_rate", 2),
        ("two contacts found (magnitudes)", "two_contact_magnitude_rate", 2),
    ]
    header = ["geometry"] + [f"{e} {c[0]}" for e in ests for c in cols]
    header += ["frames", "patches (missed)", "two-contact frames"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    rows = list(summary["geometries"].items()) + [("all", summary["average"])]
    for name, per in rows:
        cells = [name]
        counts = ("-", "-", "-")
        for e in ests:
            st = per.get(e)
            for _, key, d in cols:
                cells.append(_fmt(st.get(key, float("nan")), d) if st else "-")
            if st and e == ests[0] and "n_wrench" in st:
                counts = (
                    str(int(st["n_wrench"])),
                    f"{int(st['n_patches_scored'])} ({int(st['n_patches_missed'])})",
                    str(int(st["n_two_contact"])),
                )
        cells += list(counts)
        lines.append("| " + " | ".join(cells) + " |")
    lines.append(
        f"\nwrench scores over frames with true |f| >= {th['wrench_min_n']:g} N: torque err = "
        "|tau - tau_gt| / |tau_gt| about the mesh origin; centroid errors from each true patch "
        f"of >= {th['patch_min_n']:g} N (force-weighted centroid) to its matched estimated "
        "patch (area-weighted `centroid`, normal-force-weighted `pressure_centroid`); patch "
        "area / truth: median over matched patches; two "
        "contacts found: exactly two estimated patches, each force within "
        f"{100 * th['patch_force_tol']:g} % (as vectors, or as magnitudes); torque err vs "
        "untouched positions: against the truth's forces at the nodes' untouched positions, "
        f"the published definition (counts: {ests[0]})"
    )
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


# ---------------------------------------------------------------------------------- figures
def save_figures(
    results: Sequence[TrajectoryResult], out_dir: str | Path, estimators: Sequence[str]
) -> list[Path]:
    """PNG figures: contact patch vs truth, force field arrows, net force vs truth over time."""
    import matplotlib

    matplotlib.use("Agg")

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for g, r in _heaviest_per_indenter(results).items():
        written.append(_net_force_figure(r, estimators, out / f"net_force_{g}.png"))
        if r.fields.get("frames"):
            written.append(_contact_figure(r, estimators, out / f"contact_{g}.png"))
    return written


def _heaviest_per_indenter(results: Sequence[TrajectoryResult]) -> dict[str, TrajectoryResult]:
    """Per indenter, the trajectory with fields and the largest true force (a heavy touch)."""

    def peak(r: TrajectoryResult) -> float:
        return max((float(np.linalg.norm(x.f_gt)) for x in r.records), default=0.0)

    by_geom: dict[str, TrajectoryResult] = {}
    for r in results:
        cur = by_geom.get(r.task.geometry)
        has = bool(r.fields.get("frames"))
        if cur is None or (has, peak(r)) > (bool(cur.fields.get("frames")), peak(cur)):
            by_geom[r.task.geometry] = r
    return by_geom


def _net_force_figure(r: TrajectoryResult, estimators: Sequence[str], path: Path) -> Path:
    """Net force components and magnitude against the truth over the trajectory."""
    import matplotlib.pyplot as plt

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
    fig.suptitle(f"{r.task.geometry}: net force vs ground truth (trajectory {r.task.trajectory})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _contact_figure(r: TrajectoryResult, estimators: Sequence[str], path: Path) -> Path:
    """On the frame with the largest true contact: each estimator's contact against the
    truth (top) and its node forces as arrows on the mesh (bottom)."""
    import matplotlib.pyplot as plt

    frames = r.fields["frames"]
    V = np.asarray(r.fields["vertices"])
    i_best = max(frames, key=lambda i: int(next(iter(frames[i].values()))["gt_contact"].sum()))
    per = frames[i_best]
    names = [e for e in estimators if e in per]
    interior = np.ones(len(V), bool)
    interior[np.asarray(r.fields.get("boundary", []), dtype=int)] = False
    fig = plt.figure(figsize=(5.2 * len(names), 8.5))
    for j, name in enumerate(names):
        d = per[name]
        ax = fig.add_subplot(2, len(names), j + 1)
        _contact_panel(ax, V, d["contact"], d["gt_contact"], f"{name}: contact, frame {i_best}")
        ax3 = fig.add_subplot(2, len(names), len(names) + j + 1, projection="3d")
        _force_panel(ax3, V, np.asarray(r.fields["triangles"]), interior, d, name)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _contact_panel(ax: Any, V: NDArray, est: NDArray, gt: NDArray, title: str) -> None:
    ax.scatter(V[:, 0] * 1e3, V[:, 1] * 1e3, s=4, c="0.85")
    for mask, col, lab in (
        (est & gt, "tab:green", "both"),
        (est & ~gt, "tab:red", "estimate only"),
        (~est & gt, "tab:blue", "truth only"),
    ):
        ax.scatter(V[mask, 0] * 1e3, V[mask, 1] * 1e3, s=14, c=col, label=lab)
    ax.set_aspect("equal")
    ax.set_title(f"{title}, IoU {contact_iou(est, gt):.2f}")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=7, loc="upper right")


def _force_panel(
    ax3: Any, V: NDArray, T: NDArray, interior: NDArray, d: dict[str, Any], name: str
) -> None:
    """Force field: arrows on the mesh (interior nodes; the rim carries the base's reaction),
    longest arrow drawn 15 mm long."""
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
        color=np.where(d["contact"][interior], "tab:red", "tab:gray"),
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
        + (
            f"the reference is the {res['reference_frames']} frames the recording holds)"
            if res.get("reference") == "recorded"
            else f"the first {res['reference_frames']} frames are the reference and are not scored)"
        ),
        "",
        "| estimator | " + " | ".join(c[0] for c in cols) + " |",
        "|" + "---|" * (len(cols) + 1),
    ]
    for name, st in res["estimators"].items():
        cells = [_fmt(st[k], 2) if st[k] is not None else "-" for _, k in cols]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
