"""Issue 18 item 4: net force and contact patch area against the mesh's node count, on fixed
deformations (docs/mesh-convergence.md).

Tracks each deformation once per mesh (227 / 390 / 749 / 1500 nodes, each fitted onto the
reference surface the camera sees), then estimates it with ``ForceEstimator`` defaults:

- sim: simulated presses of several indenters (dataset trajectories, seed ``--seed``), the
  frames with ``--min-force`` N or more of true force, tracked by the oracle (the truth's
  displacement field on each mesh) and by the image path (optical flow + depth);
- real: the hold frames (index >= 26) of ``../shared/data/punyo-demo-0-press``, reference 0-4,
  the Punyo profile.

Per mesh it prints the median over frames of |f_est| and of the contact patch area (sum of the
lumped areas of the contact nodes), each relative to the finest mesh's on the same frame, and
the support (nodes, cm^2, and its area relative to the finest mesh's). ``--cache FILE`` keeps the tracked (U, dp) between runs.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/mesh_convergence.py \\
        [--only sim-oracle sim-image real] [--cache /tmp/meshconv.pkl]

``--eval-seeds S [S ...]`` measures the patch area on many more frames instead: the
evaluation's (``bubble-rt eval --seed S --mesh M``, 400 frames) on each mesh, every
single-patch frame of 1 N and more against the same frame on the finest mesh and against the
truth (about 80 s per seed).
"""

from __future__ import annotations

import argparse
import os
import pickle
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from bubble_rt import eval as ev
from bubble_rt.estimation.estimator import EstimatorConfig, ForceEstimator
from bubble_rt.estimation.pipeline import Pipeline

MESHES = ("227", "390", "749", "1500")
#: ../shared/data beside the clone (a worktree in /work/wt/NAME: the same as /work/main's)
REAL = next(
    (
        p / "shared" / "data" / "punyo-demo-0-press"
        for p in Path(__file__).resolve().parents[1:4]
        if (p / "shared" / "data" / "punyo-demo-0-press").exists()
    ),
    Path("../shared/data/punyo-demo-0-press"),
)
REAL_HOLD = range(26, 31)
SIM_INDENTERS = ("round", "point", "square", "line")


def _frames(pipe: Pipeline, frames: list[Any]) -> list[tuple[np.ndarray, float]]:
    out = []
    for fr in frames:
        d = pipe.deform(fr)
        out.append((np.array(d.U, dtype=np.float64), float(d.dp)))
    return out


def track_sim(flow: str, seed: int, n_frames: int, min_force: float) -> dict[str, Any]:
    """Per mesh: {"mesh", "pressure_pa", "frames": [(U, dp)], "f_gt": [...]}, sim presses."""
    from bubble_rt.estimation.deformation import FlowSettings

    per_mesh: dict[str, Any] = {m: {"mesh": [], "pressure_pa": [], "frames": []} for m in MESHES}
    labels = []
    for g in SIM_INDENTERS:
        traj = ev.simulate_trajectory(g, 0, n_frames, seed, render=flow != "oracle")
        keep = [
            i for i, f in enumerate(traj.frames) if np.linalg.norm(f.truth.net_force) >= min_force
        ]
        if not keep:
            continue
        labels += [(g, i, float(np.linalg.norm(traj.frames[i].truth.net_force))) for i in keep]
        for m in MESHES:
            mesh = ev.estimator_mesh(m, traj)
            pipe = Pipeline(
                mesh,
                traj.camera,
                _reference(traj.reference_frames),
                flow=FlowSettings(method=flow) if flow == "oracle" else FlowSettings(),
            )
            tracked = _frames(pipe, traj.frames)
            for i in keep:
                per_mesh[m]["mesh"].append(mesh)
                per_mesh[m]["pressure_pa"].append(pipe.reference.pressure_pa)
                per_mesh[m]["frames"].append(tracked[i])
    return {"labels": labels, "per_mesh": per_mesh, "profile": "sim"}


def _reference(frames: list[Any]) -> Any:
    from bubble_rt.estimation.deformation import Reference

    return Reference.capture(frames)


def track_real() -> dict[str, Any]:
    """Per mesh: the shared press's hold frames tracked on the fitted mesh (Punyo profile)."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(REAL)
    wr = np.array([rec[i].wrench[:3] for i in range(len(rec))])
    truth = np.linalg.norm(wr - wr[:5].mean(0), axis=1)
    per_mesh: dict[str, Any] = {}
    for m in MESHES:
        pipe = Pipeline.capture([rec[i] for i in range(5)], rec.camera, mesh=m, fit=True)
        tracked = _frames(pipe, [rec[i] for i in REAL_HOLD])
        per_mesh[m] = {
            "mesh": [pipe.mesh] * len(tracked),
            "pressure_pa": [pipe.reference.pressure_pa] * len(tracked),
            "frames": tracked,
        }
    labels = [("press", i, float(truth[i])) for i in REAL_HOLD]
    return {"labels": labels, "per_mesh": per_mesh, "profile": "punyo"}


def estimate(data: dict[str, Any], config: EstimatorConfig | None = None) -> dict[str, Any]:
    """Per mesh, per frame: |f_est| (N), patch area (m^2), support nodes and area (m^2),
    solve and refit times (ms), and the spread sum |f_i| / |f_est|. ``config``: default, EstimatorConfig with the data's sensor
    profile's ambient pressure."""
    from bubble_rt.sensor import PROFILES

    config = config or EstimatorConfig(ambient_pa=PROFILES[data["profile"]].ambient_pa)
    out: dict[str, Any] = {}
    for m, d in data["per_mesh"].items():
        rows = []
        cache: dict[int, ForceEstimator] = {}
        for mesh, p, (U, dp) in zip(d["mesh"], d["pressure_pa"], d["frames"], strict=True):
            key = id(mesh)
            if key not in cache:
                cache[key] = ForceEstimator(mesh, config, SimpleNamespace(pressure_pa=p))
            est = cache[key]
            e = est.estimate(U, dp)
            a = est.model.areas
            net = float(np.linalg.norm(e.net_force))
            rows.append(
                (
                    net,
                    float(a[e.contact].sum()),
                    int(e.support.sum()),
                    float(a[e.support].sum()),
                    e.timings_ms["solve"],
                    e.timings_ms["refit"],
                    # the nodal forces' spread: 1 for forces that all point alike
                    float(np.linalg.norm(e.node_forces, axis=1).sum()) / max(net, 1e-12),
                )
            )
        out[m] = np.array(rows)
    return out


def _barycentric(mesh: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's containing triangle of ``mesh`` (footprint x, y; -1 outside) and its
    barycentric coordinates there (P x 3)."""
    X = np.asarray(mesh.vertices)[:, :2]
    T = np.asarray(mesh.triangles)
    a, b, c = X[T[:, 0]], X[T[:, 1]], X[T[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    tri = np.full(len(points), -1)
    lam = np.zeros((len(points), 3))
    for k, p in enumerate(points[:, :2]):
        l1 = ((p[0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[1] - a[:, 1])) / det
        l2 = ((b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (p[0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        inside = np.flatnonzero((l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9))
        if inside.size:
            t = inside[0]
            tri[k], lam[k] = t, (1 - l1[t] - l2[t], l1[t], l2[t])
    return tri, lam


def restriction(data: dict[str, Any], config: EstimatorConfig | None = None) -> str:
    """How far each coarse mesh's nodal normal forces are from the finest mesh's, restricted to
    the coarse hat functions (each fine node's force shared among the corners of the coarse
    triangle holding it, by its barycentric coordinates): per mesh, the median over frames of
    sum |f - f_restricted| / sum |f_restricted| over the coarse nodes carrying at least 5 % of
    the load (docs/mesh-convergence.md, "What the coarse meshes' forces can say")."""
    from bubble_rt.sensor import PROFILES

    config = config or EstimatorConfig(ambient_pa=PROFILES[data["profile"]].ambient_pa)
    built: dict[int, ForceEstimator] = {}  # one per mesh, as estimate() does

    def normal_forces(m: str, i: int) -> tuple[Any, np.ndarray]:
        d = data["per_mesh"][m]
        mesh, p, (U, dp) = d["mesh"][i], d["pressure_pa"][i], d["frames"][i]
        if id(mesh) not in built:
            built[id(mesh)] = ForceEstimator(mesh, config, SimpleNamespace(pressure_pa=p))
        est = built[id(mesh)]
        e = est.estimate(U, dp)
        return mesh, -np.einsum("ij,ij->i", est.model.normals, e.node_forces)

    n = len(data["per_mesh"][MESHES[-1]]["frames"])
    fine = [normal_forces(MESHES[-1], i) for i in range(n)]
    out = []
    for m in MESHES[:-1]:
        rel = []
        for i in range(n):
            mesh, f = normal_forces(m, i)
            fmesh, ff = fine[i]
            tri, lam = _barycentric(mesh, np.asarray(fmesh.vertices))
            g = np.zeros(len(f))
            ok = tri >= 0
            np.add.at(
                g, np.asarray(mesh.triangles)[tri[ok]].ravel(), (lam[ok] * ff[ok, None]).ravel()
            )
            big = np.abs(g) >= 0.05 * np.abs(g).sum()
            rel.append(np.abs(f - g)[big].sum() / max(np.abs(g)[big].sum(), 1e-12))
        out.append(f"{int(m)}: {np.median(rel):.2f} [{np.min(rel):.2f}-{np.max(rel):.2f}]")
    return "coarse forces against the finest, restricted: " + ", ".join(out)


def table(name: str, data: dict[str, Any], res: dict[str, Any]) -> str:
    """Markdown table: per mesh, median |f| / truth, median |f| and area relative to finest."""
    finest = res[MESHES[-1]]
    truth = np.array([t for _, _, t in data["labels"]])
    lines = [
        f"{name} ({len(truth)} frames)",
        "",
        "| nodes | median |f|/|f_true| | median |f|/|f_finest| (worst) "
        "| median area/area_finest (worst) | support nodes | support cm^2 "
        "| median support/support_finest (worst) | patch cm^2 | solve + refit ms "
        "| sum of abs(f_i) / abs(f) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in MESHES:
        r = res[m]
        f_rel = r[:, 0] / np.maximum(finest[:, 0], 1e-9)
        a_rel = r[:, 1] / np.maximum(finest[:, 1], 1e-12)
        worst_f = f_rel[np.argmax(np.abs(f_rel - 1))]
        worst_a = a_rel[np.argmax(np.abs(a_rel - 1))]
        s_rel = r[:, 3] / np.maximum(finest[:, 3], 1e-12)
        worst_s = s_rel[np.argmax(np.abs(s_rel - 1))]
        lines.append(
            f"| {int(m)} | {np.median(r[:, 0] / truth):.2f} "
            f"| {np.median(f_rel):.2f} ({worst_f:.2f}) | {np.median(a_rel):.2f} ({worst_a:.2f}) "
            f"| {np.median(r[:, 2]):.0f} | {1e4 * np.median(r[:, 3]):.2f} "
            f"| {np.median(s_rel):.2f} ({worst_s:.2f}) "
            f"| {1e4 * np.median(r[:, 1]):.2f} "
            f"| {np.median(r[:, 4]):.1f} + {np.median(r[:, 5]):.1f} "
            f"| {np.median(r[:, 6]):.1f} |"
        )
    return "\n".join(lines)


def eval_patches(seed: int, workers: int) -> dict[str, dict[tuple, float]]:
    """Per mesh: each single-patch frame of 1 N and more of ``bubble-rt eval --seed seed``
    (its default 400 frames, image path) -> its patch area over the truth's."""
    out: dict[str, dict[tuple, float]] = {}
    for m in MESHES:
        tasks = ev.make_tasks(
            ev.GEOMETRIES,
            ev.DEFAULT_TRAJECTORIES,
            ev.DEFAULT_FRAMES,
            mesh=m,
            estimators=("fem",),
            seed_base=seed,
        )
        results, _ = ev.run_eval(tasks, workers=workers, progress=False)
        out[m] = {
            (r.geometry, r.trajectory, r.frame): r.patch_area_ratio[0]
            for res in results
            for r in res.records
            if np.linalg.norm(r.f_gt) >= 1.0 and len(r.patch_area_ratio) == 1
        }
    return out


def eval_table(seed: int, per_mesh: dict[str, dict[tuple, float]]) -> str:
    """Patch area per frame against the finest mesh's (median, the share of frames within 10 /
    25 %, per indenter) and against the truth (median, and the median of its absolute error),
    on the frames the finest mesh matched too."""
    finest = per_mesh[MESHES[-1]]
    lines = [
        f"eval seed {seed}: single-patch frames >= 1 N",
        "| nodes | frames | area / finest, median | within 10 % | within 25 % | per indenter "
        "| area / truth, median | its abs(error), median |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m in MESHES:
        keys = [k for k in per_mesh[m] if k in finest]
        r = np.array([per_mesh[m][k] / finest[k] for k in keys])
        by: dict[str, list[float]] = {}
        for k, v in zip(keys, r, strict=True):
            by.setdefault(k[0], []).append(float(v))
        per = " / ".join(f"{g} {np.median(v):.2f}" for g, v in by.items())
        truth = np.array([per_mesh[m][k] for k in keys])
        lines.append(
            f"| {m} | {len(r)} | {np.median(r):.2f} | {np.mean(abs(r - 1) <= 0.1):.2f} "
            f"| {np.mean(abs(r - 1) <= 0.25):.2f} | {per} | {np.median(truth):.2f} "
            f"| {np.median(abs(truth - 1)):.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--only", nargs="+", default=["sim-oracle", "sim-image", "real"], help="datasets"
    )
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--frames", type=int, default=8, help="frames per simulated trajectory")
    ap.add_argument("--min-force", type=float, default=0.5, help="sim frames kept (N)")
    ap.add_argument("--cache", default=None, help="pickle of the tracked frames (reused)")
    ap.add_argument(
        "--restriction",
        action="store_true",
        help="also compare each coarse mesh's nodal forces with the finest mesh's, restricted",
    )
    ap.add_argument(
        "--eval-seeds",
        type=int,
        nargs="+",
        default=None,
        help="instead: the patch area over the evaluation's frames of these seeds, per mesh",
    )
    ap.add_argument("--workers", type=int, default=2, help="--eval-seeds' processes")
    args = ap.parse_args()
    if args.eval_seeds:
        for seed in args.eval_seeds:
            print(eval_table(seed, eval_patches(seed, args.workers)) + "\n", flush=True)
        return
    cache: dict[str, Any] = {}
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as fh:
            cache = pickle.load(fh)
    for name in args.only:
        if name not in cache:
            if name == "real":
                cache[name] = track_real()
            else:
                flow = name.split("-", 1)[1]
                cache[name] = track_sim(
                    "oracle" if flow == "oracle" else "default",
                    args.seed,
                    args.frames,
                    args.min_force,
                )
            if args.cache:
                with open(args.cache, "wb") as fh:
                    pickle.dump(cache, fh)
        print(table(name, cache[name], estimate(cache[name])), flush=True)
        if args.restriction:
            print(restriction(cache[name]), flush=True)
        print(flush=True)


if __name__ == "__main__":
    main()
