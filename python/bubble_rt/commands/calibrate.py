"""`bubble-rt calibrate`: fit E, k_f, k_u to simulated ground truth with the paper's loss."""

from __future__ import annotations

import argparse
import os

HELP = "calibrate E, k_f, k_u on simulated trajectories; writes a TOML config"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="calibration.toml", help="TOML to write ([estimator] keys)")
    p.add_argument("--quick", action="store_true", help="2 round + 1 point x 10 frames, 25 evals")
    p.add_argument("--round", type=int, default=5, help="round-indenter trajectories")
    p.add_argument("--point", type=int, default=1, help="point-indenter trajectories")
    p.add_argument("--frames", type=int, default=34, help="frames per trajectory")
    p.add_argument("--mesh", default="medium")
    p.add_argument("--flow", default="default", help="flow method (FlowSettings.method)")
    p.add_argument("--method", default="Nelder-Mead", choices=["Nelder-Mead", "Powell"])
    p.add_argument("--max-evals", type=int, default=60, help="loss evaluations")
    p.add_argument("--bound", type=float, default=10.0, help="max factor from the defaults")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--scheduler", default=None, help="Dask scheduler address")
    p.add_argument("--cache", default=None, help=".npz cache of per-frame (U, dp, truth)")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from bubble_rt.eval import FanOut
    from bubble_rt.eval import calibration as cal

    n_round, n_point, frames, max_evals = args.round, args.point, args.frames, args.max_evals
    if args.quick:
        n_round, n_point, frames, max_evals = 2, 1, 10, min(max_evals, 25)
    tasks = cal.default_trajectories(
        n_round, n_point, frames, mesh=args.mesh, flow_method=args.flow
    )
    progress = not args.no_progress
    with FanOut(workers=args.workers, scheduler=args.scheduler) as fan:
        problem = cal.build_problem(tasks, fan=fan, cache=args.cache, progress=progress)
        print(f"calibration set: {len(tasks)} trajectories, {len(problem.frames)} frames")
        res = cal.calibrate(
            problem,
            method=args.method,
            max_evals=max_evals,
            bound=args.bound,
            fan=fan,
            progress=progress,
        )
    cal.write_config(
        args.out,
        res,
        extra={
            "method": args.method,
            "trajectories": [f"{t.geometry}-{t.trajectory}" for t in tasks],
            "seed": tasks[0].seed,
            "mesh": args.mesh,
            "flow": args.flow,
        },
    )
    print("| parameter | paper default | calibrated |\n|---|---|---|")
    for k in cal.PARAMS:
        print(f"| {k} | {res.initial_params[k]:.6g} | {res.params[k]:.6g} |")
    print(
        f"\nloss {res.initial_loss:.3f} -> {res.loss:.3f} ({100 * res.improvement:.1f} % lower) "
        f"over {res.n_frames} frames, {res.evaluations} evaluations, {res.seconds:.1f} s"
    )
    print(f"wrote {args.out}")
    return 0
