"""`bubble-rt eval`: accuracy of the fem and frictionless estimators against ground truth."""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from typing import Any

HELP = "evaluate force/contact accuracy on simulated trajectories (or a real recording)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small dataset (under 5 minutes)")
    p.add_argument("--full", action="store_true", help="the paper's size: 34 x 100 per indenter")
    p.add_argument(
        "--trajectories", type=int, default=None, help="per indenter (default 4; quick 2)"
    )
    p.add_argument("--frames", type=int, default=None, help="per trajectory (default 20; quick 8)")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="master seed of the simulated trajectories (default 100000; calibration draws from "
        "1000 up, so any other seed gives trajectories nobody tuned on)",
    )
    p.add_argument("--geometries", default="round,point,line,square,split")
    p.add_argument("--estimators", default="fem,frictionless")
    p.add_argument("--mesh", default="medium", help="estimator mesh: coarse|medium|fine|<nodes>")
    p.add_argument("--flow", default="default", help="flow method (FlowSettings.method)")
    p.add_argument(
        "--config",
        default=None,
        help="configuration TOML (config dump, calibrate output): its [estimator] parameters",
    )
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (e.g. tcp://h:8786)")
    p.add_argument("--json", default=None, help="write the summary (and per-frame records) here")
    p.add_argument("--figures", default=None, help="write PNG figures into this directory")
    p.add_argument("--recording", default=None, help="evaluate on a real recording with a wrench")
    p.add_argument("--reference-frames", type=int, default=5)
    p.add_argument(
        "--force-threshold", type=float, default=1.0, help="recording contact threshold (N)"
    )
    p.add_argument("--no-progress", action="store_true")
    # ---- ROS 2 bags (bubble_rt.io.rosbag) ----
    p.add_argument("--topics", default=None, help="bag topics (see `estimate --help`)")
    p.add_argument("--depth-unit", type=float, default=None, help="bag 16UC1 metres per count")


def run(args: argparse.Namespace) -> int:
    from bubble_rt._validate import output_file

    if args.json:
        output_file("--json", args.json)  # refused before the (long) run, not after
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from bubble_rt import eval as ev
    from bubble_rt.config import ConfigError

    try:
        overrides = ev.load_config_overrides(args.config)
    except ConfigError as exc:
        print(f"bubble-rt eval: invalid configuration: {exc}", file=sys.stderr)
        return 2
    estimators = tuple(e.strip() for e in args.estimators.split(",") if e.strip())
    if args.recording:
        try:
            _run_recording(args, ev, overrides, estimators)
        except (FileNotFoundError, ValueError) as exc:  # FrameError, McapFileError, ...
            # a path, a layout or frames it cannot read; frames without a wrench
            print(f"bubble-rt eval: {exc}", file=sys.stderr)
            return 2
    else:
        _run_simulated(args, ev, overrides, estimators)
    return 0


def _run_recording(args: argparse.Namespace, ev: Any, overrides: dict, estimators: tuple) -> None:
    """``--recording``: net-force magnitude and contact detection against its wrench."""
    res = ev.evaluate_recording(
        args.recording,
        overrides=overrides,
        estimators=estimators,
        mesh=args.mesh,
        n_reference=args.reference_frames,
        force_threshold=args.force_threshold,
        bag_options={"topics": args.topics, "depth_unit": args.depth_unit},
    )
    print(ev.recording_table(res))
    if args.json:
        ev.write_json(args.json, res)


def _run_simulated(args: argparse.Namespace, ev: Any, overrides: dict, estimators: tuple) -> None:
    """Simulated trajectories against the simulator's truth: tables, figures, JSON."""
    if args.full:
        traj, frames = 34, 100
    elif args.quick:
        # one light and one heavy touch per indenter (the dataset alternates them)
        traj, frames = 2, ev.QUICK_FRAMES
    else:
        traj, frames = ev.DEFAULT_TRAJECTORIES, ev.DEFAULT_FRAMES
    traj = args.trajectories or traj
    frames = args.frames or frames
    geoms = [g.strip() for g in args.geometries.split(",") if g.strip()]
    tasks = ev.make_tasks(
        geoms,
        traj,
        frames,
        mesh=args.mesh,
        estimators=estimators,
        flow_method=args.flow,
        config=tuple(sorted(overrides.items())),
        seed_base=ev.EVAL_SEED_BASE if args.seed is None else args.seed,
    )
    if args.figures:
        # per-node fields only for each indenter's first light and heavy trajectories
        tasks = [
            replace(t, keep_fields=tuple(range(frames))) if t.trajectory < 2 else t for t in tasks
        ]
    results, summary = ev.run_eval(
        tasks, workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress
    )
    print(ev.markdown_table(summary))
    tp = summary["throughput"]
    print(
        f"\n{tp['frames']} frames x {len(estimators)} estimators in {tp['wall_s']:.1f} s "
        f"({tp['frames_per_s']:.2f} frames/s, {tp['frames_per_s_per_worker']:.2f} frames/s "
        f"per worker incl. simulation)"
    )
    if args.figures:
        for p in ev.save_figures(results, args.figures, estimators):
            print(f"figure: {p}")
    if args.json:
        payload = dict(summary)
        payload["settings"] = {
            "trajectories": traj,
            "frames": frames,
            "mesh": args.mesh,
            "flow": args.flow,
            "config": overrides,
            "geometries": geoms,
            "seed": tasks[0].seed if tasks else None,
        }
        payload["frames"] = [ev.records_to_json(r.records) for r in results]
        ev.write_json(args.json, payload)
