"""``python3 -m bubble_rt.reference``: time the CVXPY solve and the full reference pipeline."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.reference.model import vertex_normals
from bubble_rt.reference.pipeline import ReferencePipeline, ReferenceSettings
from bubble_rt.reference.problem import GroupLassoProblem
from bubble_rt.reference.raycast import render_depth

Bump = Callable[[int], NDArray[np.float64]]


def _timing_main(argv: list[str] | None = None) -> int:
    """``python3 -m bubble_rt.reference``: time the CVXPY solve and the full reference pipeline."""
    import argparse

    from bubble_rt.mesh import Mesh

    ap = argparse.ArgumentParser(description=_timing_main.__doc__)
    ap.add_argument("--mesh", default="medium", help="coarse | medium | fine")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--stride", type=int, default=ReferenceSettings.cloud_stride)
    ap.add_argument("--solve-only", action="store_true", help="time only the CVXPY solve")
    args = ap.parse_args(argv)
    mesh = Mesh.preset(args.mesh)
    V, T = mesh.vertices, mesh.triangles
    normals = vertex_normals(V, T)

    def bump(k: int) -> NDArray[np.float64]:
        """A press that slides along x and releases: node displacements (N x 3, m)."""
        amp = 4e-3 * np.sin(np.pi * (k + 0.5) / args.frames)
        cx = -0.02 + 0.04 * k / max(args.frames - 1, 1)
        c = np.exp(-((V[:, 0] - cx) ** 2 + V[:, 1] ** 2) / (2 * 0.008**2))
        c[mesh.boundary] = 0
        return -amp * c[:, None] * normals

    if args.solve_only:
        _time_solve(mesh, bump, args.frames, args.mesh)
    else:
        _time_pipeline(mesh, bump, args.frames, args.mesh, args.stride)
    return 0


def _time_solve(mesh: Any, bump: Bump, frames: int, name: str) -> None:
    """The CVXPY + Clarabel group-lasso solve alone, on noisy displacements."""
    V, T = mesh.vertices, mesh.triangles
    rng = np.random.default_rng(0)
    pb = GroupLassoProblem(V, T, mesh.boundary)
    times = []
    for k in range(frames):
        U = bump(k) + 1e-4 * rng.standard_normal(V.shape)
        U[mesh.boundary] = 0
        pb.solve(U, 30.0)
        times.append(pb.last_solve_ms)
    print(
        f"reference CVXPY+Clarabel solve, {name} ({mesh.n_nodes} nodes), "
        f"{frames} frames: p50 {np.median(times):.1f} ms, max {np.max(times):.1f} ms"
    )


def _time_pipeline(mesh: Any, bump: Bump, frames: int, name: str, stride: int) -> None:
    """The whole reference pipeline on rendered frames: a random texture warped by the
    bump's image motion, and the bumped mesh's depth."""
    import cv2
    from scipy.interpolate import griddata

    from bubble_rt.camera import Camera

    V, T = mesh.vertices, mesh.triangles
    rng = np.random.default_rng(0)
    cam = Camera.d405()
    img = cv2.GaussianBlur(rng.random((cam.height, cam.width)).astype(np.float32), (0, 0), 2.0)
    img = (255 * (img - img.min()) / (img.max() - img.min())).astype(np.uint8)
    rgb_ref = np.repeat(img[:, :, None], 3, axis=2)
    pipe = ReferencePipeline(
        V, T, mesh.boundary, cam, rgb_ref, render_depth(V, T, cam), 1e5,
        settings=ReferenceSettings(cloud_stride=stride),
    )  # fmt: skip
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    uv0, _ = cam.project(V)
    stages: dict[str, list[float]] = {}
    total = []
    for k in range(frames):
        U = bump(k)
        uv1, _ = cam.project(V + U)
        back = griddata(uv1, uv0 - uv1, (xx, yy), method="linear", fill_value=0.0)
        back = np.asarray(back, dtype=np.float32)
        rgb = np.asarray(
            cv2.remap(rgb_ref, xx + back[..., 0], yy + back[..., 1], cv2.INTER_LINEAR),
            dtype=np.uint8,
        )
        depth = render_depth(V + U, T, cam)
        t = time.perf_counter()
        out = pipe.process(rgb, depth, 1e5 + 30.0)
        total.append(1e3 * (time.perf_counter() - t))
        for key, val in out["timings_ms"].items():
            stages.setdefault(key, []).append(val)
    st = ", ".join(f"{k} {np.median(v):.0f}" for k, v in stages.items())
    print(
        f"reference pipeline, {name} ({mesh.n_nodes} nodes), 640x480, cloud stride "
        f"{stride}, {frames} frames: per frame p50 {np.median(total):.0f} ms "
        f"({1e3 / np.median(total):.2f} Hz); stages p50 ms: {st}"
    )


if __name__ == "__main__":
    raise SystemExit(_timing_main())
