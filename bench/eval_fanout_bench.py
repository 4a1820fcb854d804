"""Evaluation throughput per worker: inline vs a process pool vs a Dask LocalCluster.

Runs the same `bubble-rt eval` tasks (simulated trajectories, both estimators) three ways and
reports frames per second overall and per worker, plus whether the three gave identical
metrics. The simulator's physics cache is warmed first so the figures measure rendering,
tracking and estimation, not the one-off physics.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/eval_fanout_bench.py --json out.json
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--geometries", default="round,point")
    p.add_argument("--trajectories", type=int, default=2)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args()

    from bubble_rt import eval as ev

    geoms = [g for g in args.geometries.split(",") if g]
    tasks = ev.make_tasks(geoms, args.trajectories, args.frames, mesh="medium")
    ev.run_tasks(ev.evaluate_trajectory, tasks[:1])  # warm caches (physics, mesh presets)
    ev.run_tasks(ev.evaluate_trajectory, tasks, workers=args.workers)  # physics for all

    rows = {}
    baseline = None
    modes: list[tuple[str, dict]] = [
        ("inline", {"workers": 1}),
        (f"processes x{args.workers}", {"workers": args.workers}),
    ]
    try:
        from distributed import LocalCluster

        cluster = LocalCluster(
            n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None
        )
        modes.append((f"dask x{args.workers}", {"scheduler": cluster.scheduler_address}))
    except ImportError:
        cluster = None
    n_frames = sum(t.n_frames for t in tasks)
    for name, kw in modes:
        t0 = time.perf_counter()
        res = ev.run_tasks(ev.evaluate_trajectory, tasks, **kw)
        wall = time.perf_counter() - t0
        errs = [r.force_err_n for tr in res for r in tr.records]
        if baseline is None:
            baseline = errs
        workers = kw.get("workers", args.workers)
        rows[name] = {
            "wall_s": wall,
            "frames_per_s": n_frames / wall,
            "frames_per_s_per_worker": n_frames / wall / workers,
            "same_metrics_as_inline": max(abs(a - b) for a, b in zip(errs, baseline, strict=True))
            < 1e-9,
        }
    if cluster is not None:
        cluster.close()
    print(f"{n_frames} frames (x2 estimators), medium mesh, rendering + tracking + estimation")
    print("| mode | wall s | frames/s | frames/s per worker | same metrics |")
    print("|---|---|---|---|---|")
    for name, r in rows.items():
        print(
            f"| {name} | {r['wall_s']:.1f} | {r['frames_per_s']:.2f} | "
            f"{r['frames_per_s_per_worker']:.2f} | {r['same_metrics_as_inline']} |"
        )
    if args.json:
        ev.write_json(args.json, {"frames": n_frames, "modes": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
