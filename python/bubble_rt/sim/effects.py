"""Sensor effects: each is a stage that runs only when its scene names it.

Every stage draws from its own random stream, seeded by (scene seed, effect name, sample
index), so naming one effect never changes another's noise and the same scene and seed give
identical output. What stays fixed across frames (where the depth holes sit, the exposure
drift's phase) comes from a stream of its own. The physics effects ("friction", "gas_compression", and the slow gas drift
"gas_temperature_drift" / "gas_leak" through :func:`gas_scale`) are settings handed to the
physics, not stages here; "oracle" replaces rendering (see simulator.py).
"""

from __future__ import annotations

import functools
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.sim.effect_names import GAS_DRIFT_EFFECTS

#: Offset of the sample index used for reference (tare) frames, so they never share a stream
#: with trajectory frames.
REFERENCE_STREAM = 1 << 40
#: Sample index of an effect's per-scene stream (what stays fixed across frames).
SCENE_STREAM = 1 << 41


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
    """Gaussian noise of two parts, then the depth rounded to the sensor's depth unit
    ``step_m`` (the D405 reports 0.1 mm; 0: none):

    - per pixel, sigma = sigma_m + sigma_per_m2 * z^2 (m; the z^2 term is the textbook stereo
      law, the constant what the D405 shows at 6-10 cm);
    - correlated over ``corr_px`` pixels (a Gaussian kernel's standard deviation), of RMS
      ``corr_sigma_m`` (m): a stereo match errs over its whole window, so the D405's noise
      survives smoothing over millimetres, where the estimator reads it (docs/sim-noise.md).
    """
    z = np.asarray(depth, dtype=np.float32)
    sigma = np.float32(p.get("sigma_m", 0.0)) + np.float32(p["sigma_per_m2"]) * z * z
    noisy = z + fast_normal(rng, z.shape) * sigma
    if p.get("corr_sigma_m", 0.0) > 0:
        noisy += np.float32(p["corr_sigma_m"]) * correlated_normal(rng, z.shape, p["corr_px"])
    step = np.float32(p.get("step_m", 0.0))
    if step > 0:
        noisy = np.round(noisy / step) * step
    return np.where((z > 0) & (noisy > 0), noisy, np.float32(0.0)).astype(np.float32)


def correlated_normal(
    rng: np.random.Generator, shape: tuple[int, ...], corr_px: float
) -> NDArray[np.float32]:
    """A unit-variance Gaussian field (float32) correlated over ``corr_px`` pixels: white
    noise blurred by a Gaussian kernel of that standard deviation, divided by the blur's
    exact gain on white noise (the sum of the squared kernel weights, per axis)."""
    import cv2

    s = max(float(corr_px), 0.3)
    k = 2 * int(np.ceil(4.0 * s)) + 1
    g = cv2.getGaussianKernel(k, s, cv2.CV_64F)[:, 0]
    white = fast_normal(rng, shape)
    return np.asarray(cv2.GaussianBlur(white, (k, k), s) / float(np.sum(g * g)), np.float32)


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], cell_px: float) -> NDArray:
    """A smooth random field (H x W float32, about unit variance) varying over ``cell_px``."""
    import cv2

    h, w = shape
    cell = max(2.0, cell_px)
    gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
    f = cv2.resize(
        rng.standard_normal((gh, gw)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    # The spread from a subsample: the field is smooth, and a full-image std costs 1 ms.
    return np.asarray(f / max(float(f[::4, ::4].std()), 1e-6), dtype=np.float32)


@functools.lru_cache(maxsize=8)
def scene_field(seed: int, effect: str, shape: tuple[int, int], cell_px: float) -> NDArray:
    """The smooth field of one effect fixed for a whole scene (its stream SCENE_STREAM),
    computed once per scene and image size (read-only)."""
    f = _smooth_field(effect_rng(seed, effect, SCENE_STREAM), shape, cell_px)
    f.flags.writeable = False
    return f


def _normal_cdf(x: NDArray[np.float32]) -> NDArray[np.float32]:
    """The standard normal CDF to about 3e-4 (a tanh form, several times cheaper than ndtr)."""
    x = np.asarray(x, dtype=np.float32)
    return np.float32(0.5) * (
        np.float32(1.0) + np.tanh(np.float32(0.7978846) * (x + np.float32(0.044715) * x * x * x))
    )


def depth_dropouts(
    depth: NDArray[np.float32],
    p: dict[str, float],
    rng: np.random.Generator,
    t: float,
    field: NDArray | None = None,
) -> NDArray[np.float32]:
    """Invalid blobs (depth 0) where a stereo camera finds no match, plus a few isolated
    saturated outliers at ``outlier_depth`` (the real D405 reports 6.5535 m).

    A pixel at range z is invalid with probability ``f + (1 - f) * sigmoid((near_m - z) /
    near_width_m)``: the near-range limit below which the D405's disparity search finds
    nothing (``near_m`` 0: none), over a base rate ``f`` that is ``fraction`` everywhere, or,
    when ``far_m > near_m``, falls linearly from ``fraction`` at ``near_m`` to 0 at ``far_m``
    (the real frames have no holes past about 90 mm). Which pixels: a smooth field of blob size
    ``blob_px`` fixed per scene (``field``, see :func:`scene_field`; real holes stay where they
    are, frame after frame; None: drawn from ``rng``), perturbed each frame by ``flicker`` (in the field's standard deviations), so hole
    edges flicker as the real ones do.
    """
    out = depth.copy()
    valid = out > 0
    if not valid.any():
        return out
    shape = (depth.shape[0], depth.shape[1])
    if field is None:
        field = _smooth_field(rng, shape, p["blob_px"])
    if p.get("flicker", 0.0) > 0:
        jitter = _smooth_field(rng, shape, max(2.0, 0.5 * p["blob_px"]))
        field = (field + np.float32(p["flicker"]) * jitter) / np.float32(
            np.sqrt(1.0 + p["flicker"] ** 2)
        )
    z = out[valid]
    near = p.get("near_m", 0.0)
    w = np.float32(max(p.get("near_width_m", 1e-3), 1e-6))
    with np.errstate(over="ignore"):
        ramp = np.float32(1.0) / (np.float32(1.0) + np.exp((z - np.float32(near)) / w))
    f = min(max(p["fraction"], 0.0), 1.0)
    far = p.get("far_m", 0.0)
    if far > near:  # the base rate falls linearly from near_m to nothing at far_m
        f = f * np.clip((np.float32(far) - z) / np.float32(far - near), 0.0, 1.0)
    prob = f + (1.0 - f) * (ramp if near > 0 else 0.0)
    # The field's normal quantile against the pixel's probability: invalid blobs.
    drop = np.zeros(shape, bool)
    drop[valid] = _normal_cdf(field[valid]) < prob
    out[drop] = 0.0
    n_out = int(round(p["outlier_fraction"] * valid.sum()))
    if n_out > 0:
        idx = rng.choice(np.flatnonzero(valid.ravel()), size=n_out, replace=False)
        out.reshape(-1)[idx] = np.float32(p["outlier_depth"])
    return out


def depth_jumps(
    depth: NDArray[np.float32], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.float32]:
    """Mixed pixels at depth edges: readings off the surface by millimetres to centimetres.

    At the edge of a hole (the near-range limit, grazing views) a stereo camera mixes the
    membrane with what lies past it, or aliases the disparity, and reports a depth off the
    surface, mostly behind it (issue 18's phantom: a 19 mm jump where the real D405 is
    usually blind). Within ``edge_px`` of a hole edge, small blobs (``blob_px``) covering ``rate`` of
    the band each frame report the local surface depth (the nearest valid depth, for pixels
    inside the hole) plus an excess drawn from an exponential of mean ``scale_m``, capped at
    ``max_m``, behind the surface for a share ``behind_share`` of them and in front for the
    rest. A share ``hole_share`` of them fall on the hole side (pixels that are otherwise
    invalid), the rest on valid pixels. Run after "depth_dropouts" (it needs holes).
    """
    import cv2

    out = depth.copy()
    valid = out > 0
    if p["rate"] <= 0 or valid.all() or not valid.any():
        return out
    k = max(1, int(round(p["edge_px"])))
    # Square (separable, fast) neighbourhoods.
    kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    v8 = valid.astype(np.uint8)
    hole_side = (cv2.dilate(v8, kernel) > 0) & ~valid
    valid_side = (cv2.erode(v8, kernel) == 0) & valid
    shape = (depth.shape[0], depth.shape[1])
    u = _smooth_field(rng, shape, p["blob_px"])
    # Choose the band pixels whose field is in the top ``rate`` quantile of each side.
    hs = min(max(p["hole_share"], 0.0), 1.0)
    chosen = np.zeros(shape, bool)
    n_band = int(hole_side.sum() + valid_side.sum())
    for side, share in ((hole_side, hs), (valid_side, 1.0 - hs)):
        n = int(round(p["rate"] * n_band * share))
        if n <= 0 or not side.any():
            continue
        vals = u[side]
        if n >= vals.size:
            chosen |= side
            continue
        thresh = np.partition(vals, vals.size - n)[vals.size - n]
        chosen |= side & (u >= thresh)
    if not chosen.any():
        return out
    # The local surface under a hole: the nearest valid depths (a dilation of the valid ones).
    big = np.ones((4 * k + 1, 4 * k + 1), np.uint8)
    local = np.where(valid, out, cv2.dilate(out, big))  # holes are 0: the max is a valid one
    excess = rng.exponential(max(p["scale_m"], 0.0), size=int(chosen.sum()))
    excess = np.minimum(excess, p["max_m"]).astype(np.float32)
    # Most read behind the surface (an aliased disparity); the rest in front of it.
    excess[rng.random(excess.size) >= p["behind_share"]] *= -1
    base = local[chosen]
    ok = base > 0
    idx = np.flatnonzero(chosen.ravel())[ok]
    out.reshape(-1)[idx] = np.maximum(base[ok] + excess[ok], np.float32(1e-4))
    return out


def rgb_noise(
    rgb: NDArray[np.uint8], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.uint8]:
    """The colour camera's noise, made the way its image pipeline makes it.

    The image is sampled through an RGGB Bayer mosaic, each photosite gets Gaussian noise of
    ``sigma`` (8-bit levels), the mosaic is demosaiced (OpenCV's VNG) and an edge-preserving
    denoiser (a bilateral filter, ``denoise_levels`` in levels over ``denoise_px`` pixels; 0:
    none) smooths it. What comes out is what the D405 shows and white noise does not: noise
    correlated between neighbours (0.2 both ways) and channels (0.4-0.6), and about 1.7x
    stronger on edges than on flat areas, which is where the optical flow reads it
    (docs/sim-noise.md, "Texture and image noise"). A grey image, or one narrower than 3
    pixels, gets the noise and the denoiser only.
    """
    import cv2

    if rgb.ndim != 3 or min(rgb.shape[:2]) < 3:  # OpenCV demosaics 3 x 3 and larger only
        raw = rgb.astype(np.float32) + np.float32(p["sigma"]) * fast_normal(rng, rgb.shape)
        return _denoise(_adc(raw), p)
    mosaic = np.empty(rgb.shape[:2], np.float32)
    mosaic[0::2, 0::2] = rgb[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = rgb[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = rgb[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = rgb[1::2, 1::2, 2]
    mosaic += np.float32(p["sigma"]) * fast_normal(rng, mosaic.shape)
    # OpenCV names a mosaic by its second row: RGGB is "BG".
    return _denoise(np.asarray(cv2.cvtColor(_adc(mosaic), cv2.COLOR_BayerBG2RGB_VNG)), p)


def _adc(x: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Rounded and saturated to 8 bits, as the sensor's converter does."""
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _denoise(img: NDArray[np.uint8], p: dict[str, float]) -> NDArray[np.uint8]:
    import cv2

    if p.get("denoise_levels", 0.0) <= 0:
        return img
    return np.asarray(cv2.bilateralFilter(img, 5, p["denoise_levels"], p["denoise_px"]))


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


# ---------------------------------------------------------------------- slow drift
# The slow-drift effects read *drift time*: scene time times ``rates.time_scale``, so an hour of
# drift plays in a minute of frames at ``time_scale = 60``. The membrane and the contact still
# move at scene speed; only these effects are compressed.
def illumination_ramp(p: dict[str, float], t_drift: float) -> float:
    """How far the LEDs have settled at drift time ``t_drift`` (s): 0 at the start, tending to
    1 with time constant ``settle_s`` (0: settled at once)."""
    tau = p["settle_s"]
    if t_drift <= 0:
        return 0.0
    return 1.0 if tau <= 0 else float(1.0 - np.exp(-t_drift / tau))


def illumination_drift(
    rgb: NDArray[np.uint8], p: dict[str, float], rng: np.random.Generator, t: float
) -> NDArray[np.uint8]:
    """LEDs warming up: the image gain falls by ``gain_loss`` (a fraction) and a flat offset of
    ``offset`` levels (8-bit, stray light and black level) builds up, both settling as
    :func:`illumination_ramp` at drift time ``t`` (s). Deterministic: no random draw."""
    import cv2

    r = illumination_ramp(p, t)
    if r == 0.0:
        return rgb
    gain = max(1.0 - p["gain_loss"] * r, 0.0)
    return np.asarray(cv2.convertScaleAbs(rgb, alpha=gain, beta=p["offset"] * r))


def gas_temperature_k(p: dict[str, float], t_drift: float) -> float:
    """Gas temperature (K) at drift time ``t_drift`` (s): ``temperature_k`` until ``start_s``,
    then a linear ramp of ``kelvin`` over ``ramp_s``, then flat (the camera warming the air)."""
    ramp = p["ramp_s"]
    x = t_drift - p["start_s"]
    frac = (1.0 if x > 0 else 0.0) if ramp <= 0 else min(max(x / ramp, 0.0), 1.0)
    return float(p["temperature_k"] + p["kelvin"] * frac)


def gas_amount(p: dict[str, float], t_drift: float) -> float:
    """Gas left (fraction of the sealed amount) at drift time ``t_drift`` (s): a leak losing
    ``fraction_per_hour`` of what is left each hour (exponential decay)."""
    f = min(max(p["fraction_per_hour"], 0.0), 0.999)
    return float((1.0 - f) ** (max(t_drift, 0.0) / 3600.0))


def gas_scale(
    temperature: dict[str, float] | None, leak: dict[str, float] | None, t_drift: float
) -> float:
    """The sealed gas's p V product relative to the seal (n T / n0 T0, the ideal gas law) at
    drift time ``t_drift`` (s); None: that effect is not named."""
    s = 1.0
    if temperature is not None:
        s *= gas_temperature_k(temperature, t_drift) / max(temperature["temperature_k"], 1e-9)
    if leak is not None:
        s *= gas_amount(leak, t_drift)
    return s


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
    "depth_jumps": ("depth", depth_jumps),
    "rgb_noise": ("rgb", rgb_noise),
    "exposure_drift": ("rgb", exposure_drift),
    "illumination_drift": ("rgb", illumination_drift),
}
#: Image stages that read drift time (scene time times ``rates.time_scale``).
DRIFT_TIME_STAGES = ("illumination_drift",)
PRESSURE_STAGES: dict[str, Callable[..., Any]] = {
    "pressure_noise": pressure_noise,
    "pressure_quantization": pressure_quantization,
}
PHYSICS_EFFECTS = ("friction", "gas_compression", *GAS_DRIFT_EFFECTS)


def apply_image_effects(
    effects: tuple[tuple[str, tuple[tuple[str, float], ...]], ...],
    seed: int,
    index: int,
    t: float,
    rgb: NDArray[np.uint8] | None,
    depth: NDArray[np.float32] | None,
    time_scale: float = 1.0,
) -> tuple[NDArray[np.uint8] | None, NDArray[np.float32] | None]:
    """Run the named image stages (only those, in IMAGE_STAGES order) on one frame's images.
    ``t``: scene time (s); the DRIFT_TIME_STAGES see ``t * time_scale``."""
    named = dict(effects)
    for name, (target, fn) in IMAGE_STAGES.items():
        if name not in named:
            continue
        p = dict(named[name])
        t_stage = t * time_scale if name in DRIFT_TIME_STAGES else t
        # exposure_drift's phase comes from stream 0 so it is the same for every frame.
        rng = effect_rng(seed, name, 0 if name == "exposure_drift" else index)
        if target == "depth" and depth is not None:
            if name == "depth_dropouts":
                # Where the holes sit is the scene's: real holes stay put.
                shape = (depth.shape[0], depth.shape[1])
                field = scene_field(int(seed), name, shape, float(p["blob_px"]))
                depth = fn(depth, p, rng, t, field=field)
            else:
                depth = fn(depth, p, rng, t)
        elif target == "rgb" and rgb is not None:
            rgb = fn(rgb, p, rng, t_stage)
    return rgb, depth
