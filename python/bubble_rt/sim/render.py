"""Depth and RGB images of the membrane's inner surface seen by the sensor's camera.

A thin facade over the C++ z-buffer rasteriser (``bubble_rt._core.render_mesh``): exact depth for
planar triangles, perspective-correct texture coordinates, deterministic, GIL released.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.sim.texture import MembraneTexture


@dataclass
class RenderResult:
    """depth: H x W float32 camera z (m), 0 where nothing; rgb: H x W x 3 uint8 or None;
    face: H x W int32 index of the visible triangle, -1 where nothing."""

    depth: NDArray[np.float32]
    rgb: NDArray[np.uint8] | None
    face: NDArray[np.int32]


class MembraneRenderer:
    """Renders a membrane mesh whose material coordinates are fixed.

    Args:
        camera: the sensor camera (pinhole; distortion is not rendered and is rejected).
        triangles: T x 3 int mesh connectivity.
        material_xy: M x 2 (or M x 3) rest-state material coordinates (m), used as texture
            coordinates so the pattern moves with the material.
        texture: the membrane's pattern (default MembraneTexture(): the dots).
        shading: modulate the texture by |cos| of the view angle (a light at the camera).
    """

    def __init__(
        self,
        camera: Camera,
        triangles: NDArray[np.integer],
        material_xy: NDArray[np.float64],
        texture: MembraneTexture | None = None,
        shading: bool = True,
    ) -> None:
        if camera.has_distortion:
            raise ValueError("the rasteriser renders pinhole cameras only; set distortion to zeros")
        self.camera = camera
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.texture = texture or MembraneTexture()
        self.texcoords = self.texture.texcoords(np.asarray(material_xy, dtype=np.float64))
        if len(self.texcoords) <= int(self.triangles.max(initial=-1)):
            raise ValueError("material_xy must have a row for every vertex the triangles use")
        self.shading = shading

    def render(self, vertices_mesh: NDArray[np.float64], rgb: bool = True) -> RenderResult:
        """Render vertices (M x 3, mesh frame, m). ``rgb=False`` skips texturing (depth only)."""
        from bubble_rt import _core

        v = self.camera.to_camera(np.asarray(vertices_mesh, dtype=np.float64))
        if len(v) != len(self.texcoords):
            raise ValueError(
                f"vertices must have {len(self.texcoords)} rows (one per material point), "
                f"got {len(v)}"
            )
        c = self.camera
        depth, img, face = _core.render_mesh(
            np.ascontiguousarray(v),
            self.triangles,
            self.texcoords,
            self.texture.image,
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            c.width,
            c.height,
            rgb,
            self.shading,
        )
        return RenderResult(depth=depth, rgb=img, face=face)


def render_depth(
    camera: Camera, vertices_mesh: NDArray[np.float64], triangles: NDArray[np.integer]
) -> NDArray[np.float32]:
    """Depth image (H x W float32, m, 0 where nothing) of any triangle mesh (mesh frame)."""
    from bubble_rt import _core

    v = camera.to_camera(np.asarray(vertices_mesh, dtype=np.float64))
    depth, _, _ = _core.render_mesh(
        np.ascontiguousarray(v),
        np.ascontiguousarray(triangles, dtype=np.int32),
        np.zeros((len(v), 2)),
        np.zeros((1, 1), np.uint8),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.width,
        camera.height,
        False,
        False,
    )
    return np.asarray(depth)


def bench(repeats: int = 50, sim_nodes: int = 2000) -> dict[str, float]:
    """Render time (ms, median and min over ``repeats``) of the default dome mesh at the D405's
    640 x 480: depth only, and depth + textured RGB."""
    import time

    from bubble_rt.mesh import Mesh

    mesh = Mesh.generate(sim_nodes)
    ren = MembraneRenderer(Camera.d405(), mesh.triangles, mesh.vertices)
    out: dict[str, float] = {}
    for rgb in (False, True):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            ren.render(mesh.vertices, rgb=rgb)
            times.append((time.perf_counter() - t0) * 1e3)
        key = "rgbd" if rgb else "depth"
        out[f"{key}_median_ms"] = float(np.median(times))
        out[f"{key}_min_ms"] = float(np.min(times))
    return out


if __name__ == "__main__":  # python3 -m bubble_rt.sim.render
    for k, v in bench().items():
        print(f"{k}: {v:.1f}")
