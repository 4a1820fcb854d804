"""The simulator's effects by name: every effect a scene may name (``[effects]``), with its
parameters and their defaults, declared once for the scene parser (:mod:`bubble_rt.sim.scene`),
the effects themselves (:mod:`bubble_rt.sim.effects`) and the dataset generator. Imports
nothing (docs/simulator.md, "Effects")."""

from __future__ import annotations

#: Effects that change the sealed gas per frame (``bubble_rt.sim.effects.gas_scale``).
GAS_DRIFT_EFFECTS = ("gas_temperature_drift", "gas_leak")

#: Every effect a scene may name, with its parameters and their defaults.
EFFECT_DEFAULTS: dict[str, dict[str, float]] = {
    # Physics effects (change the simulated state).
    "friction": {"mu": 0.5},
    "gas_compression": {},
    # Camera effects, matched to the real D405 of the untouched Punyo frames
    # (docs/sim-noise.md; `python3 -m bubble_rt.sim.sensor_stats` measures both sides).
    # depth_noise: temporal sigma = sigma_m + sigma_per_m2 z^2 (m) per pixel, plus a part of
    # RMS corr_sigma_m (m) correlated over corr_px pixels, then rounded to the depth unit
    # step_m; the real sensor is flat over 60-100 mm, not the textbook z^2.
    "depth_noise": {
        "sigma_m": 1.0e-5,
        "sigma_per_m2": 0.0,
        "step_m": 1.0e-4,
        "corr_sigma_m": 4.8e-5,
        "corr_px": 4.5,
    },
    # depth_dropouts: holes where the stereo match fails; probability f + (1 - f) *
    # sigmoid((near_m - z) / near_width_m), f = fraction falling to 0 at far_m (m); blobs of
    # blob_px fixed per scene, edges perturbed per frame by flicker; outlier_fraction of the
    # valid pixels saturated at outlier_depth (m; real readers turn those into holes, so 0).
    "depth_dropouts": {
        "fraction": 0.11,
        "blob_px": 10.0,
        "near_m": 0.0608,
        "near_width_m": 0.0013,
        "far_m": 0.092,
        "flicker": 0.12,
        "outlier_fraction": 0.0,
        "outlier_depth": 6.5535,
    },
    # depth_jumps: mixed pixels at hole edges; blobs of blob_px covering rate of the band of
    # edge_px around each hole per frame, hole_share of them inside the hole, reading the
    # local surface plus an exponential excess of mean scale_m, capped at max_m (m).
    "depth_jumps": {
        "rate": 0.025,
        "edge_px": 3.0,
        "blob_px": 25.0,
        "hole_share": 0.95,
        "behind_share": 0.6,
        "scale_m": 0.01,
        "max_m": 0.045,
    },
    # rgb_noise: the colour pipeline's noise: Gaussian of sigma (8-bit levels) on each
    # photosite of an RGGB mosaic, demosaiced, then an edge-preserving denoiser of
    # denoise_levels (levels; 0: none) over denoise_px (pixels).
    "rgb_noise": {"sigma": 4.0, "denoise_levels": 10.0, "denoise_px": 1.5},
    "exposure_drift": {"amplitude": 0.08, "period_s": 6.0},
    # Slow drift (docs/simulator.md "Drift"), read in drift time (scene time x
    # rates.time_scale). illumination_drift: LED warm-up, the gain falls by gain_loss (fraction)
    # and an offset of offset levels builds up, settling with time constant settle_s (s).
    "illumination_drift": {"gain_loss": 0.05, "offset": 3.0, "settle_s": 900.0},
    # gas_temperature_drift: the sealed air warms from temperature_k (K) by kelvin (K), a
    # linear ramp over ramp_s (s) from start_s (s); the pressure follows the ideal gas law with
    # the membrane's volume change (the physics solves each frame at the new gas state).
    "gas_temperature_drift": {
        "kelvin": 3.0,
        "ramp_s": 3600.0,
        "start_s": 0.0,
        "temperature_k": 296.15,
    },
    # gas_leak: the sealed air loses fraction_per_hour of its amount each hour.
    "gas_leak": {"fraction_per_hour": 0.002},
    # Pressure sensor effects.
    "pressure_noise": {"sigma_pa": 5.0},
    "pressure_quantization": {"step_pa": 1.0},
    # Timing effects.
    "timestamp_jitter": {"sigma_s": 0.002},
    "dropped_frames": {"probability": 0.03},
    # Oracle correspondences: no image rendered, the frame's truth carries exact displacements.
    "oracle": {},
}

#: Effects that need rendered images (none may go with "oracle", which renders none).
IMAGE_EFFECTS = (
    "depth_noise",
    "depth_dropouts",
    "depth_jumps",
    "rgb_noise",
    "exposure_drift",
    "illumination_drift",
)
