"""Speed of the simulator's physics: a 100-frame trajectory at the default resolution.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/sim_bench.py [--nodes 2000]
        [--indenter round] [--frictionless]

Trajectory (round indenter, mu = 0.5 unless --frictionless): 40 frames pressing 12 mm
into the dome top, 40 frames sliding 15 mm along +x, 20 frames releasing. Prints time per
frame, Newton iterations, factorisations and the physical figures (force, pressure).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bubble_rt.sim.indenters import preset
from bubble_rt.sim.physics import ContactSettings, MembraneSim, default_rest_mesh


def trajectory(top: float, n: int = 100) -> list[np.ndarray]:
    poses = []
    n_press, n_slide = int(0.4 * n), int(0.4 * n)
    n_release = n - n_press - n_slide
    for k in range(n):
        T = np.eye(4)
        if k < n_press:
            depth, x = 0.012 * (k + 1) / n_press, 0.0
        elif k < n_press + n_slide:
            depth, x = 0.012, 0.015 * (k + 1 - n_press) / n_slide
        else:
            depth, x = 0.012 * (1 - (k + 1 - n_press - n_slide) / n_release), 0.015
        T[:3, 3] = (x, 0.0, top - depth)
        poses.append(T)
    return poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--indenter", default="round")
    ap.add_argument("--frictionless", action="store_true")
    args = ap.parse_args()

    t0 = time.perf_counter()
    mesh = default_rest_mesh(args.nodes)
    t1 = time.perf_counter()
    friction = None if args.frictionless else 0.5
    sim = MembraneSim(mesh, contact=ContactSettings(friction=friction))
    ref = sim.inflate()
    t2 = time.perf_counter()
    print(f"mesh {mesh.n_nodes} nodes, {mesh.n_triangles} triangles: generated in {t1 - t0:.2f} s")
    print(
        f"inflate: {t2 - t1:.2f} s, {ref.iterations} Newton iterations, dome "
        f"{1e3 * ref.vertices[:, 2].max():.2f} mm, V {1e6 * ref.volume_m3:.1f} cm^3"
    )
    indenter = preset(args.indenter)
    sim.stats = dict.fromkeys(sim.stats, 0)
    times, iters, fz, dp, sub = [], [], [], [], []
    for T in trajectory(float(ref.vertices[:, 2].max()), args.frames):
        a = time.perf_counter()
        s = sim.solve(indenter, T)
        times.append(time.perf_counter() - a)
        if not s.converged:
            print(f"frame {len(times) - 1} did not converge")
        iters.append(s.iterations)
        sub.append(s.substeps)
        f = s.contact_forces.sum(0)
        fz.append(f)
        dp.append(s.pressure_pa - ref.pressure_pa)
    times_a = np.array(times)
    F = np.array(fz)
    k_max = int(np.argmax(-F[:, 2]))
    print(
        f"{args.frames} frames ({args.indenter}, friction {friction}): total "
        f"{times_a.sum():.1f} s, {1e3 * times_a.mean():.0f} ms/frame "
        f"(median {1e3 * np.median(times_a):.0f}, max {1e3 * times_a.max():.0f})"
    )
    print(
        f"Newton iterations/frame {np.mean(iters):.1f} (max {max(iters)}), substeps max "
        f"{max(sub)}, factorisations {sim.stats['factorizations']}, CG iterations "
        f"{sim.stats['cg_iterations']}"
    )
    print(
        f"peak push {-F[k_max, 2]:.2f} N at frame {k_max}, pressure rise {dp[k_max]:.0f} Pa; "
        f"end of slide force {np.round(F[int(0.8 * args.frames) - 1], 2).tolist()} N"
    )


if __name__ == "__main__":
    main()
