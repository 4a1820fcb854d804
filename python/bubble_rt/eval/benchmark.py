"""The benchmark suite behind `bubble-rt bench`: speed per mesh, the reference pipeline, and
what accuracy costs in time.

All figures come from one run on the same rendered 640 x 480 simulated frames:

- per mesh (coarse 227 / medium 390 / fine 749 nodes) and flow method: end-to-end latency of
  ``Pipeline.process(frame)`` (flow + lifting + solve + post) p50 / p99, rate
  (1000 / p50 latency, Hz: one frame after the other, each finished before the next starts;
  not the throughput of the daemon's two overlapped stages, which a 30 Hz camera paces), the
  per-stage medians from ``Estimate.timings_ms`` (the depth fill runs beside the flow and is
  not a stage of its own: ``lift`` is what remains of the tracking after the flow) and the
  solver's iterations;
- the paper-faithful ``bubble_rt.reference.ReferencePipeline`` on the same frames: median time
  per frame, the speedup ratio (reference p50 / product p50 at the default setting) and how far
  its outputs are from the product's (net force difference, contact IoU between the two);
- a sweep over flow method and resolution, solver tolerance and mesh size; each point has a
  median time, the mean net-force error and the contact mIoU against ground truth; the Pareto
  front over (time down, force error down, mIoU up) is reported and plotted, default marked.

Timing uses ``time.perf_counter``; warm-up frames are excluded. Set OPENBLAS_NUM_THREADS=1.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bubble_rt.eval import (
    SimTrajectory,
    contact_iou,
    estimator_config,
    estimator_mesh,
    flow_settings,
    simulate_trajectory,
)
from bubble_rt.mesh import PRESETS

MESHES = PRESETS
STAGES = ("flow", "lift", "solve", "refit", "post")


@dataclass(frozen=True)
class BenchSettings:
    """What to run. ``quick`` sizes everything for CI (under 3 minutes here)."""

    frames: int = 30
    warmup: int = 3
    geometry: str = "round"
    trajectory: int = 1  # odd trajectories are the dataset's heavy touches
    seed: int = 424_242
    meshes: tuple[str, ...] = MESHES
    #: first entry is the default setting; "default" means FlowSettings().method
    flow_methods: tuple[str, ...] = (
        "default",
        "dis_ultrafast",
        "dis_fast",
        "dis_medium",
        "farneback",
    )
    reference_frames: int = 6
    reference_meshes: tuple[str, ...] = MESHES
    sweep: bool = True
    sweep_frames: int = 12
    sweep_scales: tuple[float, ...] = (0.5, 1.0)
    sweep_tolerances: tuple[float, ...] = (5e-2, 5e-3, 5e-5)
    #: estimator parameter overrides (E, k_f, k_u, k_const, k_linear; from ``--config``)
    estimator: tuple[tuple[str, float], ...] = ()
    #: simulator physics backend (None: the real one; tests pass a stand-in)
    physics: Any = None

    @classmethod
    def quick(cls) -> BenchSettings:
        return cls(
            frames=16,
            warmup=2,
            flow_methods=("default", "dis_fast"),
            reference_frames=3,
            reference_meshes=("medium",),
            sweep_frames=8,
            sweep_scales=(0.5, 1.0),
            sweep_tolerances=(5e-3, 5e-5),
        )


def _pct(x: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(x, float), q)) if len(x) else float("nan")


@dataclass
class RunStats:
    """Timings and accuracy of one estimator configuration over the benchmark frames."""

    latency_ms: list[float] = field(default_factory=list)
    stages_ms: dict[str, list[float]] = field(default_factory=dict)
    iterations: list[float] = field(default_factory=list)
    force_err: list[float] = field(default_factory=list)
    ious: list[float] = field(default_factory=list)
    net_forces: list[np.ndarray] = field(default_factory=list)
    contacts: list[np.ndarray] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        p50 = _pct(self.latency_ms, 50)
        ious = [v for v in self.ious if not math.isnan(v)]
        return {
            "hz": 1000.0 / p50 if p50 > 0 else float("nan"),
            "latency_ms": {"p50": p50, "p99": _pct(self.latency_ms, 99)},
            "stages_ms": {k: _pct(v, 50) for k, v in self.stages_ms.items()},
            "iterations": _pct(self.iterations, 50),
            "force_err_n": float(np.mean(self.force_err)) if self.force_err else float("nan"),
            "miou": float(np.mean(ious)) if ious else float("nan"),
            "frames": len(self.latency_ms),
        }


def _resolve_methods(methods: Sequence[str]) -> tuple[str, ...]:
    """Names with "default" replaced by FlowSettings().method, duplicates dropped."""
    from bubble_rt.estimation.deformation import FlowSettings

    out: list[str] = []
    for m in methods:
        m = FlowSettings().method if m == "default" else m
        if m not in out:
            out.append(m)
    return tuple(out)


def _flow_settings(method: str, scale: float | None = None) -> Any:
    s = flow_settings(method)
    if scale is not None:
        s = replace(s, scale=scale)
    return s


def _solver_config(config: Any, tol: float | None) -> Any:
    """The estimator config with the solver's relative tolerance (``eps_rel``) set."""
    if tol is None:
        return config
    return replace(config, solver=replace(config.solver, eps_rel=tol))


def run_product(
    mesh: Any,
    traj: SimTrajectory,
    frames: Sequence[Any],
    *,
    flow: Any,
    config: Any,
    warmup: int,
    gt_masks: Sequence[np.ndarray],
) -> RunStats:
    """Time the FEM pipeline's ``process`` on ``frames[warmup:]`` after ``warmup`` untimed
    frames (``gt_masks`` aligned with ``frames``)."""
    from bubble_rt.estimation.pipeline import Pipeline

    est = Pipeline.capture(
        traj.reference_frames, traj.camera, mesh=mesh, fit=False, config=config, flow=flow
    )
    frames = list(frames)
    for fr in frames[:warmup]:
        est.process(fr)
    st = RunStats()
    for i in range(warmup, len(frames)):
        fr = frames[i]
        t0 = time.perf_counter()
        e = est.process(fr)
        st.latency_ms.append(1e3 * (time.perf_counter() - t0))
        for k in STAGES:
            if k in e.timings_ms:
                st.stages_ms.setdefault(k, []).append(float(e.timings_ms[k]))
        st.iterations.append(float(getattr(e.info, "iterations", float("nan"))))
        f = np.asarray(e.net_force, float)
        st.force_err.append(float(np.linalg.norm(f - np.asarray(fr.truth.net_force, float))))
        st.ious.append(contact_iou(np.asarray(e.contact, bool), gt_masks[i]))
        st.net_forces.append(f)
        st.contacts.append(np.asarray(e.contact, bool))
    return st


def run_reference(
    mesh: Any,
    traj: SimTrajectory,
    frames: Sequence[Any],
    *,
    gt_masks: Sequence[np.ndarray],
    warmup: int = 1,
) -> RunStats:
    """Time bubble_rt.reference.ReferencePipeline on ``frames[warmup:]`` (``gt_masks`` aligned
    with ``frames``); the warm-up frames run untimed (CVXPY compiles its problem on the first).
    The reference runs the paper's method with the paper's parameters (its own defaults), not
    the product's: it is what the product is compared against."""
    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.reference import ReferencePipeline

    reference = Reference.capture(traj.reference_frames)
    pipe = ReferencePipeline.from_mesh(mesh, traj.camera, reference)
    frames = list(frames)
    for fr in frames[:warmup]:
        pipe.process(fr.rgb, fr.depth, fr.pressure_pa)
    st = RunStats()
    for i in range(warmup, len(frames)):
        fr = frames[i]
        t0 = time.perf_counter()
        e = pipe.process(fr.rgb, fr.depth, fr.pressure_pa)
        st.latency_ms.append(1e3 * (time.perf_counter() - t0))
        for k in STAGES:
            if k in e["timings_ms"]:
                st.stages_ms.setdefault(k, []).append(float(e["timings_ms"][k]))
        f = np.asarray(e["net_force"], float)
        st.force_err.append(float(np.linalg.norm(f - np.asarray(fr.truth.net_force, float))))
        st.ious.append(contact_iou(np.asarray(e["contact"], bool), gt_masks[i]))
        st.net_forces.append(f)
        st.contacts.append(np.asarray(e["contact"], bool))
    return st


def pareto_front(points: Sequence[dict[str, Any]]) -> list[int]:
    """Indices of points not dominated in (time_ms down, force_err_n down, miou up)."""
    idx = []
    for i, p in enumerate(points):
        dominated = False
        for j, q in enumerate(points):
            if i == j:
                continue
            pm = p["miou"] if not math.isnan(p["miou"]) else -1.0
            qm = q["miou"] if not math.isnan(q["miou"]) else -1.0
            no_worse = (
                q["time_ms"] <= p["time_ms"] and q["force_err_n"] <= p["force_err_n"] and qm >= pm
            )
            better = q["time_ms"] < p["time_ms"] or q["force_err_n"] < p["force_err_n"] or qm > pm
            if no_worse and better:
                dominated = True
                break
        if not dominated:
            idx.append(i)
    return idx


def run_bench(
    settings: BenchSettings, *, progress: bool = True, log: Any = print
) -> dict[str, Any]:
    """Run the whole suite; returns the JSON-ready result."""
    t_start = time.perf_counter()
    settings = replace(settings, flow_methods=_resolve_methods(settings.flow_methods))
    n_total = settings.warmup + max(settings.frames, settings.sweep_frames)
    log(f"simulating {n_total} frames ...")
    traj = simulate_trajectory(
        settings.geometry, settings.trajectory, n_total, settings.seed, physics=settings.physics
    )
    frames_all = traj.frames
    base_config = estimator_config(settings.estimator)
    result: dict[str, Any] = {
        "settings": {
            "frames": settings.frames,
            "warmup": settings.warmup,
            "geometry": settings.geometry,
            "image": list(traj.frames[0].shape[::-1]) if traj.frames[0].shape else None,
            "flow_methods": list(settings.flow_methods),
        },
        "meshes": {},
        "sweep": [],
    }
    meshes: dict[str, Any] = {}
    gts: dict[str, list[np.ndarray]] = {}
    for name in settings.meshes:
        meshes[name] = estimator_mesh(name, traj)
        gts[name] = [np.asarray(f.truth.contact_mask(meshes[name]), bool) for f in frames_all]

    for name in settings.meshes:
        entry, default_stats = _bench_mesh(
            settings, traj, meshes[name], gts[name], base_config, name, log
        )
        if name in settings.reference_meshes and settings.reference_frames > 0:
            _bench_reference(
                settings, traj, meshes[name], gts[name], entry, default_stats, name, log
            )
        result["meshes"][name] = entry

    if settings.sweep:
        result["sweep"] = run_sweep(settings, traj, meshes, gts, base_config, log)
        front = pareto_front(result["sweep"])
        for i, p in enumerate(result["sweep"]):
            p["pareto"] = i in front
    result["seconds"] = time.perf_counter() - t_start
    return result


def _bench_mesh(
    settings: BenchSettings,
    traj: SimTrajectory,
    mesh: Any,
    gt: list[np.ndarray],
    base_config: Any,
    name: str,
    log: Any,
) -> tuple[dict[str, Any], Any]:
    """The product on one mesh with every flow method; the entry reports the first (the
    default) method's figures, which are also returned as run stats for the reference."""
    n = settings.warmup + settings.frames
    entry: dict[str, Any] = {"nodes": int(mesh.n_nodes), "flows": {}}
    default_flow = settings.flow_methods[0]
    for method in settings.flow_methods:
        st = run_product(
            mesh,
            traj,
            traj.frames[:n],
            flow=_flow_settings(method),
            config=base_config,
            warmup=settings.warmup,
            gt_masks=gt[:n],
        )
        summ = st.summary()
        entry["flows"][method] = summ
        log(
            f"  {name:6s} {mesh.n_nodes:4d} nodes  {method:14s} "
            f"{summ['hz']:7.1f} Hz  p50 {summ['latency_ms']['p50']:7.2f} ms  "
            f"p99 {summ['latency_ms']['p99']:7.2f} ms  err {summ['force_err_n']:.2f} N  "
            f"mIoU {summ['miou']:.3f}"
        )
        if method == default_flow:
            default_stats = st
    d = entry["flows"][default_flow]
    entry.update({k: d[k] for k in ("hz", "latency_ms", "stages_ms", "iterations")})
    entry.update(
        {"force_err_n": d["force_err_n"], "miou": d["miou"], "reference_ms": None, "speedup": None}
    )
    return entry, default_stats


def _bench_reference(
    settings: BenchSettings,
    traj: SimTrajectory,
    mesh: Any,
    gt_all: list[np.ndarray],
    entry: dict[str, Any],
    product: Any,
    name: str,
    log: Any,
) -> None:
    """The paper-faithful reference pipeline on the same frames: its time per frame, the
    speed-up and how far its outputs are from the product's (adds to ``entry``)."""
    timed = traj.frames[settings.warmup : settings.warmup + settings.frames]
    gt = gt_all[settings.warmup : settings.warmup + settings.frames]
    # One untimed warm-up frame, then frames spread over the second half of the timed set
    # (the contact phase), where the outputs are worth comparing.
    n_t = len(timed)
    sel = np.unique(np.linspace(n_t // 2, n_t - 1, min(settings.reference_frames, n_t)).astype(int))
    ref = run_reference(
        mesh, traj, [timed[0]] + [timed[i] for i in sel], gt_masks=[gt[0]] + [gt[i] for i in sel]
    )
    rs = ref.summary()
    diffs = [
        float(np.linalg.norm(a - product.net_forces[i]))
        for a, i in zip(ref.net_forces, sel, strict=True)
    ]
    agree = [contact_iou(a, product.contacts[i]) for a, i in zip(ref.contacts, sel, strict=True)]
    agree = [v for v in agree if not math.isnan(v)]
    prod_err = float(np.mean([product.force_err[i] for i in sel]))
    p50 = entry["latency_ms"]["p50"]
    entry.update(
        {
            "reference_ms": rs["latency_ms"]["p50"],
            "speedup": rs["latency_ms"]["p50"] / p50,
            "reference": {
                "latency_ms": rs["latency_ms"],
                "stages_ms": rs["stages_ms"],
                "frames": len(sel),
                "force_err_n": rs["force_err_n"],
                "miou": rs["miou"],
                "product_force_err_n_same_frames": prod_err,
                "net_force_diff_n": float(np.mean(diffs)) if diffs else None,
                "contact_iou_vs_product": float(np.mean(agree)) if agree else None,
            },
        }
    )
    log(
        f"  {name:6s} reference {rs['latency_ms']['p50']:.0f} ms/frame -> speedup "
        f"{entry['speedup']:.1f}x; |f_ref - f| {entry['reference']['net_force_diff_n']:.3f}"
        f" N; err ref {rs['force_err_n']:.2f} N vs product {prod_err:.2f} N"
    )


def run_sweep(
    settings: BenchSettings,
    traj: SimTrajectory,
    meshes: dict[str, Any],
    gts: dict[str, list[np.ndarray]],
    base_config: Any,
    log: Any = print,
) -> list[dict[str, Any]]:
    """Accuracy/time points: one axis at a time around the default (medium mesh, default flow,
    default tolerance), plus the mesh axis; each point timed on ``sweep_frames`` frames."""
    # Warm-up frames, then sweep_frames spread evenly over the trajectory: solve cost depends
    # on the content (free space, approach, contact), so every point sees the same mix.
    w = settings.warmup
    rest = np.arange(w, len(traj.frames))
    pick = rest[np.linspace(0, len(rest) - 1, min(settings.sweep_frames, len(rest))).astype(int)]
    sel = list(range(w)) + [int(i) for i in pick]
    frames = [traj.frames[i] for i in sel]
    default_mesh = "medium" if "medium" in meshes else next(iter(meshes))
    default_method = settings.flow_methods[0]
    points: list[tuple[str, str, float | None, float | None]] = [
        (default_mesh, default_method, None, None)
    ]
    for m in settings.flow_methods:
        for sc in settings.sweep_scales:
            points.append((default_mesh, m, sc, None))
    for t in settings.sweep_tolerances:
        points.append((default_mesh, default_method, None, t))
    for name in meshes:
        points.append((name, default_method, None, None))
    seen: set[tuple[Any, ...]] = set()
    out = []
    for mesh_name, method, scale, tol in points:
        flow = _flow_settings(method, scale)
        config = _solver_config(base_config, tol)
        key = (mesh_name, repr(flow), repr(config.solver))
        if key in seen:
            continue
        seen.add(key)
        st = run_product(
            meshes[mesh_name],
            traj,
            frames,
            flow=flow,
            config=config,
            warmup=settings.warmup,
            gt_masks=[gts[mesh_name][i] for i in sel],
        )
        s = st.summary()
        is_default = scale is None and tol is None and method == default_method
        is_default = is_default and mesh_name == default_mesh
        pt = {
            "mesh": mesh_name,
            "nodes": int(meshes[mesh_name].n_nodes),
            "flow": method,
            "flow_scale": float(getattr(flow, "scale", float("nan"))),
            "solver_tol": tol,
            "time_ms": s["latency_ms"]["p50"],
            "force_err_n": s["force_err_n"],
            "miou": s["miou"],
            "iterations": s["iterations"],
            "default": is_default,
        }
        out.append(pt)
        log(
            f"  sweep {mesh_name:6s} {method:14s} scale {pt['flow_scale']:.2f} tol {tol} -> "
            f"{pt['time_ms']:.2f} ms, err {pt['force_err_n']:.2f} N, mIoU {pt['miou']:.3f}"
        )
    return out


# ---------------------------------------------------------------------------------- reporting
def _f(x: Any, d: int = 2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.{d}f}"


def mesh_table(result: dict[str, Any]) -> str:
    """Markdown: per mesh and flow method rate, latency, stages, iterations, reference."""
    lines = [
        "| mesh | nodes | flow | Hz | p50 ms | p99 ms | flow | lift | solve | refit | post "
        "| iters | force err (N) | mIoU | reference ms | speedup |",
        "|" + "---|" * 16,
    ]
    for name, e in result["meshes"].items():
        for method, s in e["flows"].items():
            st = s["stages_ms"]
            lines.append(
                f"| {name} | {e['nodes']} | {method} | {_f(s['hz'], 1)} | "
                f"{_f(s['latency_ms']['p50'])} | {_f(s['latency_ms']['p99'])} | "
                + " | ".join(_f(st.get(k)) for k in STAGES)
                + f" | {_f(s['iterations'], 0)} | {_f(s['force_err_n'])} | {_f(s['miou'], 3)} | "
                + (
                    f"{_f(e['reference_ms'], 0)} | {_f(e['speedup'], 1)}x |"
                    if method == next(iter(e["flows"])) and e.get("reference_ms")
                    else "- | - |"
                )
            )
    return "\n".join(lines)


def reference_table(result: dict[str, Any]) -> str:
    lines = [
        "| mesh | reference ms | product p50 ms | speedup | ref force err (N) "
        "| product force err (N) | mean abs(f_ref - f) (N) | contact IoU ref vs product |",
        "|" + "---|" * 8,
    ]
    for name, e in result["meshes"].items():
        r = e.get("reference")
        if not r:
            continue
        lines.append(
            f"| {name} | {_f(e['reference_ms'], 0)} | {_f(e['latency_ms']['p50'])} | "
            f"{_f(e['speedup'], 1)}x | {_f(r['force_err_n'])} | "
            f"{_f(r['product_force_err_n_same_frames'])} | {_f(r['net_force_diff_n'], 3)} | "
            f"{_f(r['contact_iou_vs_product'], 3)} |"
        )
    return "\n".join(lines)


def sweep_table(result: dict[str, Any], pareto_only: bool = False) -> str:
    lines = [
        "| mesh | flow | scale | solver tol | time ms | force err (N) | mIoU | iters | "
        "Pareto | default |",
        "|" + "---|" * 10,
    ]
    pts = sorted(result.get("sweep", []), key=lambda p: p["time_ms"])
    for p in pts:
        if pareto_only and not p.get("pareto"):
            continue
        lines.append(
            f"| {p['mesh']} | {p['flow']} | {_f(p['flow_scale'])} | "
            f"{p['solver_tol'] if p['solver_tol'] is not None else 'default'} | "
            f"{_f(p['time_ms'])} | {_f(p['force_err_n'])} | {_f(p['miou'], 3)} | "
            f"{_f(p['iterations'], 0)} | {'*' if p.get('pareto') else ''} | "
            f"{'default' if p.get('default') else ''} |"
        )
    return "\n".join(lines)


def plot_sweep(result: dict[str, Any], path: str | Path) -> Path:
    """PNG: time vs force error for every sweep point, Pareto front joined, default starred."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = result.get("sweep", [])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    t = np.array([p["time_ms"] for p in pts])
    e = np.array([p["force_err_n"] for p in pts])
    m = np.array([p["miou"] if p["miou"] is not None else np.nan for p in pts], float)
    lo = float(np.nanmin(m)) if np.isfinite(m).any() else 0.0
    hi = float(np.nanmax(m)) if np.isfinite(m).any() else 1.0
    sc = ax.scatter(
        t, e, c=np.nan_to_num(m, nan=lo), cmap="viridis", s=40, vmin=lo, vmax=max(hi, lo + 1e-3)
    )
    fig.colorbar(sc, ax=ax, label="contact mIoU")
    front = sorted((p for p in pts if p.get("pareto")), key=lambda p: p["time_ms"])
    if front:
        ax.plot(
            [p["time_ms"] for p in front],
            [p["force_err_n"] for p in front],
            "r--",
            lw=1,
            label="Pareto front",
        )
    for p in pts:
        lab = f"{p['mesh'][0]}/{p['flow']}"
        if p["flow_scale"] and not math.isnan(p["flow_scale"]) and p["flow_scale"] != 1.0:
            lab += f"@{p['flow_scale']:g}"
        if p["solver_tol"] is not None:
            lab += f" tol{p['solver_tol']:g}"
        ax.annotate(lab, (p["time_ms"], p["force_err_n"]), fontsize=6, alpha=0.8)
        if p.get("default"):
            ax.scatter(
                [p["time_ms"]], [p["force_err_n"]], marker="*", s=250, c="red", label="default"
            )
    ax.set_xscale("log")
    ax.set_xlabel("time per frame (ms, p50)")
    ax.set_ylabel("net-force error (N)")
    ax.set_title("accuracy vs time (640x480 simulated frames)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
