"""The pattern printed (or painted) on the membrane's inner surface, as the camera sees it.

The texture lives in material coordinates: the (x, y) position (metres) of a membrane point in
the simulation's rest (uninflated) state. Because a material point keeps its coordinates when
the membrane stretches or slides, the rendered pattern moves with the material and optical
flow between rendered frames is the real material motion.

Two patterns, named by a sensor's bubble (``bubble_rt.sensor.BubblePhysics.texture``) or a
scene (``[sensor] texture``):

* ``dots``: the simulator's own bubble, dense small dots on a light membrane.
* ``punyo``: a real Punyo's, bright paint splashed over a dark membrane under green LEDs:
  millimetre blobs with sharp edges, wide dark areas with a faint speckle. Matched on the
  shared untouched Punyo frames at the tracker's nodes (docs/sim-noise.md, "Texture and
  image noise"): the local contrast and image gradient where the flow is read, which set the
  flow noise together with the camera's noise.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class DotPattern:
    """Random dots on a light membrane with low-frequency blotches.

    Attributes:
        dot_spacing: mean distance between dot centres (m).
        dot_radius: (min, max) dot radius (m).
    """

    dot_spacing: float = 1.1e-3
    dot_radius: tuple[float, float] = (0.22e-3, 0.45e-3)


@dataclass(frozen=True)
class SplatterPattern:
    """Bright paint splashed on a dark membrane: the thresholded sum of Gaussian random fields.

    Attributes:
        ink_rgb: the bare membrane's colour (8-bit levels, as lit inside the sensor).
        paint_rgb: the paint's colour (8-bit levels; saturates where it exceeds 255).
        coverage: share of the membrane the paint covers.
        scales_m, weights: correlation lengths (m) and weights of the random fields whose
            sum, thresholded at the ``1 - coverage`` quantile, makes the blobs: the finest
            roughens their edges, the middle one sets their size, the coarsest clusters them.
        paint_variation: relative RMS of the paint's brightness, over paint_variation_scale_m.
        speckle_rgb: RMS (levels per channel) of the fine speckle everywhere, over the texel.
        edge_blur_m: the edges' blur (m).
    """

    ink_rgb: RGB = (7.0, 83.0, 34.0)
    paint_rgb: RGB = (70.0, 264.0, 172.0)
    coverage: float = 0.4
    scales_m: tuple[float, ...] = (0.15e-3, 0.6e-3, 2.5e-3)
    weights: tuple[float, ...] = (0.35, 1.0, 0.7)
    paint_variation: float = 0.2
    paint_variation_scale_m: float = 2.0e-3
    speckle_rgb: RGB = (1.1, 3.6, 1.8)
    edge_blur_m: float = 0.07e-3


Pattern = DotPattern | SplatterPattern

#: The patterns by name (the ``texture`` of a bubble or a scene).
PATTERNS: dict[str, Pattern] = {"dots": DotPattern(), "punyo": SplatterPattern()}


@dataclass(frozen=True)
class TextureSettings:
    """A membrane pattern on a texel grid.

    Attributes:
        half_extent: (x, y) half sizes (m) of the textured area around the origin.
        texel: texel size (m); 0.1 mm is about half a camera pixel at the membrane.
        pattern: the pattern (:data:`PATTERNS`).
        seed: pattern seed (a fixed property of the printed membrane, not of a scene's noise).
    """

    half_extent: tuple[float, float] = (0.062, 0.045)
    texel: float = 1.0e-4
    pattern: Pattern = field(default_factory=DotPattern)
    seed: int = 0

    @classmethod
    def named(cls, name: str, seed: int = 0) -> TextureSettings:
        """The settings of the pattern called ``name``; ValueError lists the known ones."""
        if name not in PATTERNS:
            raise ValueError(f"unknown texture {name!r}; known: {', '.join(PATTERNS)}")
        return cls(pattern=PATTERNS[name], seed=seed)


class MembraneTexture:
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
    hx, hy = st.half_extent
    shape = (int(round(2 * hy / st.texel)) + 1, int(round(2 * hx / st.texel)) + 1)
    rng = np.random.default_rng(st.seed)
    if isinstance(st.pattern, SplatterPattern):
        img = _splatter(st.pattern, shape, st.texel, rng)
    else:
        img = _dots(st.pattern, shape, st.texel, st.half_extent, rng)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out


def _dots(
    p: DotPattern,
    shape: tuple[int, int],
    texel: float,
    half_extent: tuple[float, float],
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    import cv2

    h, w = shape
    # Low-frequency blotches in the background give flow something to hold on between dots.
    coarse = rng.uniform(-1, 1, (h // 40 + 2, w // 40 + 2, 3)).astype(np.float32)
    blotch = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    img: NDArray = np.empty((h, w, 3), np.float32)
    img[:] = (205.0, 190.0, 170.0)
    img += 22.0 * blotch
    n = int(4 * half_extent[0] * half_extent[1] / p.dot_spacing**2)
    centres = np.column_stack([rng.uniform(0, w - 1, n), rng.uniform(0, h - 1, n)])
    radii = rng.uniform(p.dot_radius[0], p.dot_radius[1], n) / texel
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
    return np.asarray(cv2.GaussianBlur(img, (0, 0), 1.0))


def _random_field(
    rng: np.random.Generator, shape: tuple[int, int], sigma_texels: float
) -> NDArray[np.float32]:
    """A unit-variance Gaussian random field correlated over ``sigma_texels``."""
    import cv2

    f = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma_texels)
    return np.asarray(f / max(float(f.std()), 1e-12), dtype=np.float32)


def _splatter(
    p: SplatterPattern, shape: tuple[int, int], texel: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    import cv2

    level = np.zeros(shape, np.float32)
    for scale, weight in zip(p.scales_m, p.weights, strict=True):
        level += np.float32(weight) * _random_field(rng, shape, scale / texel)
    paint = (level > np.quantile(level, 1.0 - p.coverage)).astype(np.float32)[..., None]
    shade = 1.0 + p.paint_variation * _random_field(rng, shape, p.paint_variation_scale_m / texel)
    ink, colour = (np.asarray(c, np.float32) for c in (p.ink_rgb, p.paint_rgb))
    img = (1.0 - paint) * ink + paint * shade[..., None] * colour
    img += _random_field(rng, shape, 1.0)[..., None] * np.asarray(p.speckle_rgb, np.float32)
    return np.asarray(cv2.GaussianBlur(img, (0, 0), p.edge_blur_m / texel))
