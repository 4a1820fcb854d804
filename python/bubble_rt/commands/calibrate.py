"""`bubble-rt calibrate`: fit E, k_f, k_u with the paper's loss, to simulated ground truth or
(``--recording``) to recordings that carry a force/torque wrench (there the ambient pressure,
which sets the rest tension, and the F/T rotation are fitted too by default)."""

from __future__ import annotations

import argparse
import os

HELP = (
    "calibrate E, k_f, k_u on simulated trajectories, or with the ambient pressure and the F/T "
    "rotation on wrench recordings; writes a TOML config"
)


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
    g = p.add_argument_group(
        "recordings with a wrench (instead of the simulated trajectories)",
        "loss: the force term against the recorded wrench (bias from the reference frames, "
        "F/T -> mesh rotation given or fitted), the contact term where contact truth exists",
    )
    g.add_argument(
        "--recording",
        action="append",
        default=[],
        metavar="PATH",
        help="a recording with a wrench on every frame (Punyo folder, .mcap, any layout "
        "open_recording reads); repeat for several",
    )
    g.add_argument(
        "--reference-frames",
        type=int,
        default=None,
        help="untouched reference frames per recording (default 5; the wrench bias is their "
        "mean wrench)",
    )
    g.add_argument(
        "--wrench-config",
        default=None,
        metavar="FILE",
        help="TOML with [wrench] rotation = 3 x 3 rows (F/T frame -> mesh frame; without it "
        "the rotation is fitted jointly, Kabsch inside the loss), sign = -1 (the F/T sensor "
        "reports the reaction), reference_frames = N",
    )
    g.add_argument("--max-frames", type=int, default=0, help="scored frames per recording (0: all)")
    g.add_argument(
        "--fit",
        default=None,
        help="parameters to fit, comma-separated, of E, k_f, k_u, ambient_pa (default: all; "
        "the ambient pressure sets the rest tension); the others keep the estimator's defaults",
    )


def run(args: argparse.Namespace) -> int:
    from bubble_rt._validate import output_file

    output_file("--out", args.out)  # refused before the (long) calibration, not after
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if args.recording:
        return run_recordings(args)
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
    print("| parameter | default | calibrated |\n|---|---|---|")
    for k in cal.PARAMS:
        print(f"| {k} | {res.initial_params[k]:.6g} | {res.params[k]:.6g} |")
    print(
        f"\nloss {res.initial_loss:.3f} -> {res.loss:.3f} ({100 * res.improvement:.1f} % lower) "
        f"over {res.n_frames} frames, {res.evaluations} evaluations, {res.seconds:.1f} s"
    )
    print(f"wrote {args.out}")
    return 0


def run_recordings(args: argparse.Namespace) -> int:
    """``--recording``: calibrate on recorded wrenches (bubble_rt.eval.recording_calibration)."""
    import sys

    import numpy as np

    from bubble_rt.eval import FanOut
    from bubble_rt.eval import calibration as cal
    from bubble_rt.eval import recording_calibration as rc

    try:
        wcfg = rc.load_wrench_config(args.wrench_config) if args.wrench_config else {}
        n_ref = args.reference_frames or wcfg.get("reference_frames", 5)
        sets = [
            rc.load_recording(
                path, mesh=args.mesh, n_reference=n_ref, flow=args.flow, max_frames=args.max_frames
            )
            for path in args.recording
        ]
    except rc.WrenchCalibrationError as exc:
        print(f"bubble-rt calibrate: {exc}", file=sys.stderr)
        return 2
    problem = rc.RecordingProblem(sets, rotation=wcfg.get("rotation"), sign=wcfg.get("sign", 1.0))
    print(
        f"calibration set: {len(sets)} recordings, {len(problem.frames)} frames "
        f"({problem.contact_frames} with contact truth), {n_ref} reference frames each"
    )
    max_evals = min(args.max_evals, 25) if args.quick else args.max_evals
    try:
        with FanOut(workers=args.workers, scheduler=args.scheduler) as fan:
            out = rc.calibrate_recordings(
                problem,
                method=args.method,
                max_evals=max_evals,
                bound=args.bound,
                fan=fan,
                progress=not args.no_progress,
                fit=(
                    rc.FIT_PARAMS
                    if args.fit is None
                    else [k.strip() for k in args.fit.split(",") if k.strip()]
                ),
            )
    except rc.WrenchCalibrationError as exc:
        print(f"bubble-rt calibrate: {exc}", file=sys.stderr)
        return 2
    res = out.result
    cal.write_config(
        args.out,
        res,
        extra={
            "method": args.method,
            "recordings": [str(p) for p in args.recording],
            "reference_frames": n_ref,
            "mesh": args.mesh,
            "flow": args.flow,
            **out.info(),
        },
    )
    print("| parameter | default | calibrated |\n|---|---|---|")
    for k in res.params:
        print(f"| {k} | {res.initial_params[k]:.6g} | {res.params[k]:.6g} |")
    how = "fitted (Kabsch)" if out.rotation_fitted else "given"
    print(f"\nF/T -> mesh rotation, {how}:")
    for row in out.rotation:
        print("  [" + "  ".join(f"{x:+.4f}" for x in row) + "]")
    if out.rotation_fitted and out.wrench_spread[1] < 0.05:
        print(
            "  warning: the wrenches point almost one way (spread "
            f"{np.round(out.wrench_spread, 3).tolist()}): the spin about that direction is "
            "poorly determined; press in more directions or give the rotation",
        )
    for name, b in out.biases.items():
        print(f"wrench bias {name}: [" + " ".join(f"{x:+.4f}" for x in b) + "]")
    print(
        f"\nloss {res.initial_loss:.3f} -> {res.loss:.3f} ({100 * res.improvement:.1f} % lower) "
        f"over {res.n_frames} frames, {res.evaluations} evaluations, {res.seconds:.1f} s"
    )
    print(f"wrote {args.out}")
    return 0
