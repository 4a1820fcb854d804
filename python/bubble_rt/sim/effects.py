"""Sensor effects: each is a stage that runs only when its scene names it.

Every stage draws from its own random stream, seeded by (scene seed, effect name, sample
index), so naming one effect never changes another's noise and the same scene and seed give
identical output. The physics effects ("friction", "gas_compression") are settings handed to
the physics, not stages here; "oracle" replaces rendering (see simulator.py).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Offset of the sample index used for reference (tare) frames, so they never share a stream
#: with trajectory frames.
REFERENCE_STREAM = 1 << 40


def effect_rng(seed: int, effect: str, index: int) -> np.random.Generator:
    """The random stream of one effect for one sample (frame index, or 0 for whole series)."""
    return np.random.default_rng([int(seed), zlib.crc32(effect.encode()), int(index)])


def _normal_lut() -> NDArray[np.float32]:
    from scipy.special import ndtri

    return np.asarray(ndtri((np.arange(65536) + 0.5) / 65536), dtype=np.float32)


_NORMAL_LUT = _normal_lut()


def fast_normal(rng: np.random.Generator, shape: tuple[int, ...]) -> NDArray[np.float32]:
    """Standard normal float32 samples via a 16-bit inverse-CDF table (tails cut at 4.3
    sigma): about 10x faster than ``rng.standard_normal`` for whole images, so noisy frames
    keep up with 30 Hz."""
    n = int(np.prod(shape))
    u = np.frombuffer(rng.bytes(2 * n), dtype=np.uint16)
    return _NORMAL_LUT[u].reshape(shape)


# ---------------------------------------------------------------------- image stages
def depth_noise(
    depth: NDArray[np.float32], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.float32]:
    """Gaussian noise with sigma = sigma_per_m2 * z^2 (m), as in stereo and ToF sensors."""
    z = np.asarray(depth, dtype=np.float32)
    noisy = z + fast_normal(rng, z.shape) * (np.float32(p["sigma_per_m2"]) * z * z)
    return np.where((z > 0) & (noisy > 0), noisy, np.float32(0.0)).astype(np.float32)


def depth_dropouts(
    depth: NDArray[np.float32], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.float32]:
    """Invalid blobs (depth 0) covering ``fraction`` of the valid pixels, plus a few isolated
    saturated outliers at ``outlier_depth`` (the real D405 reports 6.5535 m)."""
    import cv2

    h, w = depth.shape
    out = depth.copy()
    valid = out > 0
    if not valid.any():
        return out
    cell = max(2.0, p["blob_px"])
    gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
    field = cv2.resize(
        rng.standard_normal((gh, gw)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    if p["fraction"] > 0:
        # The threshold from a fixed subsample of the valid pixels: same statistics, 4x cheaper.
        thresh = np.quantile(field[valid][::4], 1.0 - min(p["fraction"], 1.0))
        out[valid & (field >= thresh)] = 0.0
    n_out = int(round(p["outlier_fraction"] * valid.sum()))
    if n_out > 0:
        idx = rng.choice(np.flatnonzero(valid.ravel()), size=n_out, replace=False)
        out.reshape(-1)[idx] = np.float32(p["outlier_depth"])
    return out


def rgb_noise(
    rgb: NDArray[np.uint8], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.uint8]:
    """Additive Gaussian noise (sigma in 8-bit levels), clipped."""
    import cv2

    noise = fast_normal(rng, rgb.shape) * np.float32(p["sigma"])
    return np.asarray(cv2.add(rgb, noise, dtype=cv2.CV_8U))  # rounds and saturates


def exposure_drift(
    rgb: NDArray[np.uint8], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.uint8]:
    """A slow gain drift: gain = 1 + amplitude * sin(2 pi t / period_s + phase). The phase is
    fixed per scene (the stream of index 0), so the drift is smooth across frames."""
    import cv2

    gain = 1.0 + p["amplitude"] * np.sin(2 * np.pi * t / max(p["period_s"], 1e-9) + _phase(rng))
    return np.asarray(cv2.convertScaleAbs(rgb, alpha=max(gain, 0.0)))


def _phase(rng: np.random.Generator) -> float:
    return float(rng.uniform(0, 2 * np.pi))


# ---------------------------------------------------------------------- series stages
def pressure_noise(
    values: NDArray[np.float64], p: dict[str, float], rng: np.random.Generator
) -> NDArray[np.float64]:
    """Gaussian noise on every reading (Pa)."""
    return values + rng.standard_normal(values.shape) * p["sigma_pa"]


def pressure_quantization(
    values: NDArray[np.float64], p: dict[str, float], rng: np.random.Generator
) -> NDArray[np.float64]:
    """Readings rounded to the sensor's resolution ``step_pa`` (1 Pa = 0.01 hPa)."""
    step = p["step_pa"]
    return np.round(values / step) * step if step > 0 else values


def timestamp_jitter(
    times: NDArray[np.float64], p: dict[str, float], rng: np.random.Generator
) -> NDArray[np.float64]:
    """Gaussian jitter (s) on reported timestamps; the sample itself is taken on time."""
    return times + rng.standard_normal(times.shape) * p["sigma_s"]


def dropped_frames(n: int, p: dict[str, float], rng: np.random.Generator) -> NDArray[np.bool_]:
    """Mask of frames that are delivered (False: dropped, its index is skipped)."""
    return np.asarray(rng.random(n) >= p["probability"])


#: Image stages in the order they run: (name, target, function).
IMAGE_STAGES: dict[str, tuple[str, Callable[..., Any]]] = {
    "depth_noise": ("depth", depth_noise),
    "depth_dropouts": ("depth", depth_dropouts),
    "rgb_noise": ("rgb", rgb_noise),
    "exposure_drift": ("rgb", exposure_drift),
}
PRESSURE_STAGES: dict[str, Callable[..., Any]] = {
    "pressure_noise": pressure_noise,
    "pressure_quantization": pressure_quantization,
}
PHYSICS_EFFECTS = ("friction", "gas_compression")


def apply_image_effects(
    effects: tuple[tuple[str, tuple[tuple[str, float], ...]], ...],
    seed: int,
    index: int,
    t: float,
    rgb: NDArray[np.uint8] | None,
    depth: NDArray[np.float32] | None,
) -> tuple[NDArray[np.uint8] | None, NDArray[np.float32] | None]:
    """Run the named image stages (only those) on one frame's images."""
    for name, params in effects:
        stage = IMAGE_STAGES.get(name)
        if stage is None:
            continue
        target, fn = stage
        p = dict(params)
        # exposure_drift's phase comes from stream 0 so it is the same for every frame.
        rng = effect_rng(seed, name, 0 if name == "exposure_drift" else index)
        if target == "depth" and depth is not None:
            depth = fn(depth, p, rng, t)
        elif target == "rgb" and rgb is not None:
            rgb = fn(rgb, p, rng, t)
    return rgb, depth
