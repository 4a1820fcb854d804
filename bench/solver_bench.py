"""Benchmark of the ADMM group-lasso solver against the CVXPY + Clarabel reference.

For each mesh preset, a synthetic contact presses, slides and releases over ``--frames``
frames with fresh noise every frame. The ADMM solver is warm-started frame to frame; the
reference (bubble_rt.reference.GroupLassoProblem: CVXPY + Clarabel, problem built once with
Parameters, single-threaded) is timed on a subset of the same frames in the same run.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/solver_bench.py [--tight] \
        [--frames 200] [--reference-frames 20] [--meshes coarse medium fine] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from bubble_rt.estimation.membrane import MembraneModel
from bubble_rt.estimation.solver import GroupLassoSolver, SolverSettings
from bubble_rt.mesh import PRESETS, Mesh
from bubble_rt.reference import GroupLassoProblem

K_F, K_U = 0.3322, 537592.0


def sequence(mesh: Mesh, frames: int, seed: int = 0):
    """Yield (U, dp): press to 8 mm, slide 30 mm with shear, release; 0.2 mm noise."""
    rng = np.random.default_rng(seed)
    V = mesh.vertices
    n_press = frames * 3 // 10
    n_slide = frames * 4 // 10
    a, b = np.array([-0.015, -0.005]), np.array([0.015, 0.01])
    for k in range(frames):
        if k < n_press:
            depth, s, shear = 8e-3 * (k + 1) / n_press, 0.0, 0.0
        elif k < n_press + n_slide:
            depth, s, shear = 8e-3, (k - n_press) / n_slide, 3e-3
        else:
            depth, s, shear = 8e-3 * (frames - 1 - k) / (frames - n_press - n_slide), 1.0, 0.0
        c = (1 - s) * a + s * b
        bump = np.exp(-((np.linalg.norm(V[:, :2] - c, axis=1) / 0.015) ** 2))
        U = np.zeros_like(V)
        U[:, 2] = -depth * bump
        U[:, 0] = shear * bump
        U[mesh.boundary] = 0.0
        U += rng.normal(scale=2e-4, size=U.shape)
        yield np.ascontiguousarray(U), 40_000.0 * depth


def run_mesh(name: str, settings: SolverSettings, frames: int, ref_frames: int) -> dict:
    mesh = Mesh.preset(name)
    model = MembraneModel(mesh)
    solver = GroupLassoSolver(model, K_F, K_U, settings)
    problem = GroupLassoProblem(mesh.vertices, mesh.triangles, mesh.boundary, k_f=K_F, k_u=K_U)
    ref_at = set(np.linspace(0, frames - 1, max(ref_frames, 1)).round().astype(int).tolist())
    solve_ms, wall_ms, cpu_ms, iters, ref_ms, gaps, statuses = [], [], [], [], [], [], []
    for k, (U, dp) in enumerate(sequence(mesh, frames)):
        t0, c0 = time.perf_counter(), time.thread_time()
        res = solver.solve_frame(U, dp)
        wall_ms.append(1e3 * (time.perf_counter() - t0))
        # CPU time of this thread: insensitive to other processes on a loaded machine.
        cpu_ms.append(1e3 * (time.thread_time() - c0))
        solve_ms.append(res.info.solve_time_ms)
        iters.append(res.info.iterations)
        statuses.append(res.info.status)
        if ref_frames > 0 and k in ref_at:
            t0 = time.perf_counter()
            _, obj_ref = problem.solve(U, dp)
            ref_ms.append(1e3 * (time.perf_counter() - t0))
            obj = problem.objective(res.dU, U, dp)
            gaps.append((obj - obj_ref) / max(abs(obj_ref), 1e-12))
    # The first frame is a cold start with setup-time effects; report it separately.
    warm = np.asarray(solve_ms[1:])
    ref_median = float(np.median(ref_ms)) if ref_ms else float("nan")
    return {
        "nodes": mesh.n_nodes,
        "solve_ms_p50": float(np.median(warm)),
        "solve_ms_p99": float(np.percentile(warm, 99)),
        "wall_ms_p50": float(np.median(wall_ms[1:])),
        "cpu_ms_p50": float(np.median(cpu_ms[1:])),
        "cpu_ms_p99": float(np.percentile(cpu_ms[1:], 99)),
        "first_frame_ms": float(solve_ms[0]),
        "setup_ms": float(solver._impl.setup_time_ms),
        "iterations_p50": float(np.median(iters[1:])),
        "iterations_max": int(max(iters)),
        "solved_fraction": float(np.mean([s == "solved" for s in statuses])),
        "reference_ms": ref_median,
        "reference_frames": len(ref_ms),
        "speedup": ref_median / float(np.median(warm)),
        "objective_gap_max": float(max(gaps)) if gaps else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument(
        "--reference-frames",
        type=int,
        default=20,
        help="frames (evenly spread) also solved by the reference (0 = none)",
    )
    ap.add_argument("--meshes", nargs="+", default=list(PRESETS))
    ap.add_argument("--tight", action="store_true", help="tight settings (gap ~1e-5)")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = ap.parse_args(argv)
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        print("warning: set OPENBLAS_NUM_THREADS=1 for comparable timings")
    settings = SolverSettings.tight() if args.tight else SolverSettings()
    out: dict = {
        "settings": "tight" if args.tight else "default",
        "frames": args.frames,
        "meshes": {},
    }
    print(
        f"{'mesh':>7} {'nodes':>5} {'p50 ms':>7} {'p99 ms':>7} {'cpu p50':>7} {'iters':>5} "
        f"{'ref ms':>7} {'speedup':>7} {'gap max':>9} {'solved':>6}"
    )
    for name in args.meshes:
        r = run_mesh(name, settings, args.frames, args.reference_frames)
        out["meshes"][name] = r
        print(
            f"{name:>7} {r['nodes']:>5} {r['solve_ms_p50']:>7.2f} {r['solve_ms_p99']:>7.2f} "
            f"{r['cpu_ms_p50']:>7.2f} {r['iterations_p50']:>5.0f} {r['reference_ms']:>7.1f} {r['speedup']:>7.1f} "
            f"{r['objective_gap_max']:>9.2e} {r['solved_fraction']:>6.2f}",
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
