"""`bubble-rt bench`: speed per mesh, the reference pipeline, and the accuracy/time sweep."""

from __future__ import annotations

import argparse
import os
import sys

HELP = "benchmark rate/latency per mesh, the reference pipeline and the accuracy/time sweep"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="CI-sized run (under 3 minutes)")
    p.add_argument("--json", default=None, help="write results as JSON")
    p.add_argument("--plot", default=None, help="write the accuracy/time Pareto plot (PNG)")
    p.add_argument("--frames", type=int, default=None, help="timed frames per configuration")
    p.add_argument("--meshes", default=None, help="comma list of coarse,medium,fine")
    p.add_argument("--flows", default=None, help="comma list of flow methods (first = default)")
    p.add_argument("--reference-frames", type=int, default=None, help="0 skips the reference")
    p.add_argument("--no-sweep", action="store_true")
    p.add_argument(
        "--config",
        default=None,
        help="configuration TOML (config dump, calibrate output): its [estimator] parameters",
    )


def run(args: argparse.Namespace) -> int:
    from bubble_rt._validate import output_file

    if args.json:
        output_file("--json", args.json)  # refused before the (long) run, not after
    # Single-threaded BLAS: timings must not depend on what else shares the two cores.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from dataclasses import replace

    from bubble_rt.config import ConfigError
    from bubble_rt.eval import benchmark as bm
    from bubble_rt.eval import load_config_overrides, write_json

    try:
        overrides = load_config_overrides(args.config)
    except ConfigError as exc:
        print(f"bubble-rt bench: invalid configuration: {exc}", file=sys.stderr)
        return 2
    s = bm.BenchSettings.quick() if args.quick else bm.BenchSettings()
    s = replace(s, estimator=tuple(sorted(overrides.items())))
    if args.frames:
        s = replace(s, frames=args.frames)
    if args.meshes:
        s = replace(s, meshes=tuple(m.strip() for m in args.meshes.split(",") if m.strip()))
    if args.flows:
        s = replace(s, flow_methods=tuple(m.strip() for m in args.flows.split(",") if m.strip()))
    if args.reference_frames is not None:
        s = replace(s, reference_frames=args.reference_frames)
    if args.no_sweep:
        s = replace(s, sweep=False)
    result = bm.run_bench(s)
    print()
    print(bm.mesh_table(result))
    if any(e.get("reference") for e in result["meshes"].values()):
        print()
        print(bm.reference_table(result))
    if result["sweep"]:
        print("\naccuracy vs time (all points, Pareto marked *):")
        print(bm.sweep_table(result))
    if args.plot and result["sweep"]:
        print(f"plot: {bm.plot_sweep(result, args.plot)}")
    if args.json:
        write_json(args.json, result)
        print(f"json: {args.json}")
    print(f"\nbench took {result['seconds']:.0f} s")
    return 0
