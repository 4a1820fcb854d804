"""The dot texture printed on the membrane's inner surface.

The texture lives in material coordinates: the (x, y) position (metres) of a membrane point in
the simulation's rest (uninflated) state. Because a material point keeps its coordinates when
the membrane stretches or slides, the rendered pattern moves with the material and optical
flow between rendered frames is the real material motion.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class TextureSettings:
    """A random-dot pattern.

    Attributes:
        half_extent: (x, y) half sizes (m) of the textured area around the origin.
        texel: texel size (m); 0.1 mm is about half a camera pixel at the membrane.
        dot_spacing: mean distance between dot centres (m).
        dot_radius: (min, max) dot radius (m).
        seed: pattern seed (a fixed property of the printed membrane, not of a scene's noise).
    """

    half_extent: tuple[float, float] = (0.062, 0.045)
    texel: float = 1.0e-4
    dot_spacing: float = 1.1e-3
    dot_radius: tuple[float, float] = (0.22e-3, 0.45e-3)
    seed: int = 0


class DotTexture:
    """An H x W x 3 uint8 RGB image plus the map from material coordinates to texels."""

    def __init__(self, settings: TextureSettings | None = None) -> None:
        self.settings = settings or TextureSettings()
        self.image: NDArray[np.uint8] = _make_image(self.settings)

    def texcoords(self, material_xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Texel coordinates (M x 2: column s, row t) of material points (M x 2 or M x 3, m)."""
        xy = np.asarray(material_xy, dtype=np.float64)[:, :2]
        hx, hy = self.settings.half_extent
        s = (xy[:, 0] + hx) / self.settings.texel
        t = (xy[:, 1] + hy) / self.settings.texel
        return np.ascontiguousarray(np.column_stack([s, t]))


@functools.lru_cache(maxsize=4)
def _make_image(st: TextureSettings) -> NDArray[np.uint8]:
    import cv2

    hx, hy = st.half_extent
    w = int(round(2 * hx / st.texel)) + 1
    h = int(round(2 * hy / st.texel)) + 1
    rng = np.random.default_rng(st.seed)
    # Low-frequency blotches in the background give flow something to hold on between dots.
    coarse = rng.uniform(-1, 1, (h // 40 + 2, w // 40 + 2, 3)).astype(np.float32)
    blotch = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    img: NDArray = np.empty((h, w, 3), np.float32)
    img[:] = (205.0, 190.0, 170.0)
    img += 22.0 * blotch
    n = int(4 * hx * hy / st.dot_spacing**2)
    centres = np.column_stack([rng.uniform(0, w - 1, n), rng.uniform(0, h - 1, n)])
    radii = rng.uniform(st.dot_radius[0], st.dot_radius[1], n) / st.texel
    colours = rng.uniform(10, 120, (n, 3))
    shift = 4  # sub-texel precision for cv2 drawing
    for (cx, cy), r, col in zip(centres, radii, colours, strict=True):
        cv2.circle(
            img,
            (int(cx * (1 << shift)), int(cy * (1 << shift))),
            int(r * (1 << shift)),
            tuple(float(c) for c in col),
            thickness=-1,
            lineType=cv2.LINE_AA,
            shift=shift,
        )
    # Pre-filter to about the camera's footprint of a texel to avoid aliasing when sampled.
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out
