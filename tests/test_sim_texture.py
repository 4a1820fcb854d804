"""The membrane patterns (bubble_rt.sim.texture): reproducible, and each with its own look."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.sim.texture import PATTERNS, MembraneTexture, SplatterPattern, TextureSettings


def grey(img: np.ndarray) -> np.ndarray:
    return img.astype(float) @ np.array([0.299, 0.587, 0.114])


def test_every_pattern_is_a_fixed_property_of_its_seed():
    for name in PATTERNS:
        a = MembraneTexture(TextureSettings.named(name, seed=3)).image
        b = MembraneTexture(TextureSettings.named(name, seed=3)).image
        c = MembraneTexture(TextureSettings.named(name, seed=4)).image
        assert a.dtype == np.uint8 and a.ndim == 3 and np.array_equal(a, b)
        assert not np.array_equal(a, c)
        assert not a.flags.writeable  # shared between renderers: nobody may draw on it


def test_unknown_pattern_names_the_known_ones():
    with pytest.raises(ValueError, match="unknown texture 'plaid'; known: dots, punyo"):
        TextureSettings.named("plaid")


def test_punyo_pattern_is_paint_splashed_on_a_dark_membrane():
    p = SplatterPattern()
    g = grey(MembraneTexture(TextureSettings.named("punyo")).image)
    ink, paint = grey(np.array(p.ink_rgb)), grey(np.clip(np.array(p.paint_rgb), 0, 255))
    painted = g > (ink + paint) / 2
    # The paint covers its share, in blobs about a millimetre across (texels of 0.1 mm): the
    # grey level is still correlated 1 mm away, where the dots' (0.2-0.45 mm) is not.
    assert abs(painted.mean() - p.coverage) < 0.05
    assert 0.3 < autocorrelation(g, 10) < 0.7 and autocorrelation(g, 40) < 0.2
    dots = grey(MembraneTexture().image)
    assert autocorrelation(dots, 10) < 0.1
    # Dark, green-lit ink between the blobs: the mean grey level is low.
    assert g.mean() < 120 < dots.mean()


def autocorrelation(g: np.ndarray, lag: int) -> float:
    d = g - g.mean()
    return float(np.mean(d[:, :-lag] * d[:, lag:]) / d.var())
