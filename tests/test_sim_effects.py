"""Effects: an unnamed effect costs nothing; a named one changes only its own output."""

from __future__ import annotations

import numpy as np
import pytest
from _sim_fake import FakePhysics, small_scene
from bubble_rt.sim import effects
from bubble_rt.sim.effect_names import EFFECT_DEFAULTS
from bubble_rt.sim.simulator import Simulator


def effects_defaults(name: str) -> dict[str, float]:
    return dict(EFFECT_DEFAULTS[name])


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path))


def run(eff: str = "[]", seed: int = 0, frames: int = 4):
    sim = Simulator(small_scene(eff, frames=frames, seed=seed), physics=FakePhysics())
    return sim, list(sim.frames())


def test_unnamed_effects_do_not_run(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("an unnamed effect ran")

    for name in effects.IMAGE_STAGES:
        monkeypatch.setitem(effects.IMAGE_STAGES, name, (effects.IMAGE_STAGES[name][0], boom))
    for name in effects.PRESSURE_STAGES:
        monkeypatch.setitem(effects.PRESSURE_STAGES, name, boom)
    monkeypatch.setattr(effects, "timestamp_jitter", boom)
    monkeypatch.setattr(effects, "dropped_frames", boom)
    sim, frames = run()
    assert len(frames) == 4
    assert sim.stages_run == {"render"}


def test_oracle_renders_nothing(monkeypatch):
    from bubble_rt.sim import render

    def boom(*a, **k):
        raise AssertionError("rendered in an oracle scene")

    monkeypatch.setattr(render.MembraneRenderer, "render", boom)
    sim, frames = run('["oracle"]')
    assert all(f.rgb is None and f.depth is None for f in frames)
    assert "render" not in sim.stages_run
    g = frames[-1].truth
    moved = g.displace(g.sim_reference_vertices)
    np.testing.assert_allclose(moved, g.sim_vertices, atol=1e-12)


def images(frames):
    return (
        np.stack([f.rgb for f in frames]),
        np.stack([f.depth for f in frames]),
        np.array([f.pressure_pa for f in frames]),
        np.array([f.t for f in frames]),
    )


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("BUBBLE_RT_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield images(run()[1])
    mp.undo()


def test_depth_noise_changes_only_depth(base):
    rgb, depth, p, t = images(run('["depth_noise"]')[1])
    assert (
        np.array_equal(rgb, base[0]) and np.array_equal(p, base[2]) and np.array_equal(t, base[3])
    )
    assert not np.array_equal(depth, base[1])
    assert np.array_equal(depth > 0, base[1] > 0)


def test_depth_dropouts_change_only_depth(base):
    # A uniform 10 % (no near-range limit, no fall-off) with saturated outliers.
    eff = "{ depth_dropouts = { fraction = 0.10, near_m = 0, far_m = 0, outlier_fraction = 2e-4 } }"
    rgb, depth, p, _ = images(run(eff)[1])
    assert np.array_equal(rgb, base[0]) and np.array_equal(p, base[2])
    valid0 = base[1] > 0
    dropped = valid0 & (depth == 0)
    assert 0.07 < dropped.sum() / valid0.sum() < 0.13
    assert (np.isclose(depth, 6.5535)).any()
    kept = valid0 & (depth > 0) & ~np.isclose(depth, 6.5535)
    assert np.array_equal(depth[kept], base[1][kept])


def test_rgb_noise_changes_only_rgb(base):
    rgb, depth, p, _ = images(run('["rgb_noise"]')[1])
    assert np.array_equal(depth, base[1]) and np.array_equal(p, base[2])
    # The noise is what two seeds' frames do not share (the mosaic's interpolation error on
    # the texture's sharp dots they do). Per photosite sigma; demosaicing and the denoiser
    # leave 0.6-0.8 of it on the membrane.
    other = images(run('["rgb_noise"]', seed=1)[1])[0]
    d = (rgb.astype(float) - other.astype(float)) / np.sqrt(2)
    sigma = effects_defaults("rgb_noise")["sigma"]
    assert 0.5 * sigma < d[base[1] > 0].std() < 0.95 * sigma


def test_exposure_drift_changes_only_rgb(base):
    rgb, depth, p, _ = images(run("{ exposure_drift = { amplitude = 0.2, period_s = 0.5 } }")[1])
    assert np.array_equal(depth, base[1]) and np.array_equal(p, base[2])
    ratio = rgb[..., 0][base[1] > 0].mean() / base[0][..., 0][base[1] > 0].mean()
    assert not np.array_equal(rgb, base[0]) and 0.75 < ratio < 1.25


def test_pressure_noise_and_quantization_change_only_pressure(base):
    sim, frames = run('["pressure_noise", "pressure_quantization"]')
    rgb, depth, p, _ = images(frames)
    assert np.array_equal(rgb, base[0]) and np.array_equal(depth, base[1])
    assert not np.array_equal(p, base[2])
    r = sim.pressure_readings().pressure_pa
    assert np.array_equal(r, np.round(r))  # 1 Pa = 0.01 hPa steps


def test_timestamp_jitter_changes_only_times(base):
    rgb, depth, p, t = images(run('["timestamp_jitter"]')[1])
    assert np.array_equal(rgb, base[0]) and np.array_equal(depth, base[1])
    assert np.array_equal(p, base[2])
    assert not np.array_equal(t, base[3]) and np.abs(t - base[3]).max() < 0.02


def test_dropped_frames_drop_whole_frames_only():
    _, full = run(frames=30)
    _, some = run("{ dropped_frames = { probability = 0.3 } }", frames=30)
    assert 5 < len(full) - len(some) < 20
    by_index = {f.index: f for f in full}
    for f in some:
        assert np.array_equal(f.rgb, by_index[f.index].rgb)


def test_effect_streams_are_independent():
    _, a = run('["depth_noise"]')
    _, b = run('["depth_noise", "rgb_noise"]')
    assert np.array_equal(images(a)[1], images(b)[1])


def test_same_seed_same_noise_other_seed_other_noise():
    eff = '["depth_noise", "rgb_noise", "pressure_noise"]'
    a, b, c = (images(run(eff, seed=s)[1]) for s in (1, 1, 2))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])


def test_depth_noise_grows_with_depth_squared():
    rng = np.random.default_rng(0)
    p = {"sigma_per_m2": 0.02}
    near = effects.depth_noise(np.full((200, 200), 0.05, np.float32), p, rng, 0.0)
    far = effects.depth_noise(np.full((200, 200), 0.10, np.float32), p, rng, 0.0)
    ratio = (far - 0.10).std() / (near - 0.05).std()
    assert 3.6 < ratio < 4.4


def test_pressure_noise_has_the_requested_spread():
    rng = np.random.default_rng(0)
    x = effects.pressure_noise(np.full(20000, 1e5), {"sigma_pa": 5.0}, rng)
    assert abs(x.std() - 5.0) < 0.2


# ---------------------------------------------------------------------- the D405 models
def test_depth_noise_rounds_to_the_depth_unit():
    rng = np.random.default_rng(0)
    z = np.full((100, 100), 0.08, np.float32)
    out = effects.depth_noise(z, {"sigma_m": 5e-5, "sigma_per_m2": 0.0, "step_m": 1e-4}, rng, 0.0)
    steps = out / np.float32(1e-4)
    assert np.allclose(steps, np.round(steps), atol=1e-3)
    assert len(np.unique(np.round(steps))) >= 2  # the noise still moves pixels across a step


def test_correlated_noise_has_unit_variance_and_the_requested_correlation():
    # Gaussian-blurred white noise: its autocorrelation is a Gaussian of std corr_px * sqrt(2),
    # 0.78 at a lag of corr_px and 0.37 at 2 corr_px.
    rng = np.random.default_rng(1)
    f = effects.correlated_normal(rng, (400, 600), 4.5).astype(np.float64)
    assert abs(f.std() - 1.0) < 0.05
    for lag, expect in ((4, np.exp(-(4**2) / (4 * 4.5**2))), (9, np.exp(-(9**2) / (4 * 4.5**2)))):
        r = np.mean(f[:, lag:] * f[:, :-lag]) / f.var()
        assert abs(r - expect) < 0.05, (lag, r, expect)


def test_depth_noise_survives_smoothing_only_when_correlated():
    # What the estimator sees at a node is the depth averaged over millimetres: white noise
    # averages away there, the D405's (correlated over its stereo window) does not.
    import cv2

    z = np.full((300, 300), 0.08, np.float32)
    white = {"sigma_m": 5e-5, "sigma_per_m2": 0.0, "step_m": 0.0}
    corr = {**white, "sigma_m": 0.0, "corr_sigma_m": 5e-5, "corr_px": 4.5}
    rms = {}
    for name, p in (("white", white), ("corr", corr)):
        d = effects.depth_noise(z, p, np.random.default_rng(2), 0.0).astype(np.float64) - 0.08
        assert abs(d.std() - 5e-5) < 3e-6
        rms[name] = cv2.GaussianBlur(d, (0, 0), 20.0)[40:-40, 40:-40].std()
    # Smoothed over 20 px: white falls to 5e-5 / (2 sqrt(pi) 20) = 0.7 um, the correlated
    # part to 5e-5 * 4.5 / sqrt(4.5^2 + 20^2) = 11 um.
    assert rms["white"] < 1.5e-6 and 8e-6 < rms["corr"] < 14e-6


def ramp_depth() -> np.ndarray:
    """A plane tilted from 50 mm (left) to 100 mm (right), 480 x 640."""
    return np.tile(np.linspace(0.05, 0.10, 640, dtype=np.float32), (480, 1))


D405_DROPOUTS = EFFECT_DEFAULTS["depth_dropouts"]


def dropped_by_range(out: np.ndarray, z: np.ndarray, lo: float, hi: float) -> float:
    m = (z >= lo) & (z < hi)
    return float((out[m] == 0).mean())


def test_depth_dropouts_follow_the_near_range_limit():
    z = ramp_depth()
    p = dict(D405_DROPOUTS)
    out = effects.depth_dropouts(z, p, effects.effect_rng(0, "d", 1), 0.0)
    near, w = p["near_m"], p["near_width_m"]
    assert dropped_by_range(out, z, 0.05, near - 3 * w) > 0.9  # below the D405's reach
    assert 0.2 < dropped_by_range(out, z, near - w, near + w) < 0.8  # a ragged edge
    mid = 0.5 * (near + p["far_m"])
    assert 0.2 * p["fraction"] < dropped_by_range(out, z, mid - 0.002, mid + 0.002) < p["fraction"]
    assert dropped_by_range(out, z, p["far_m"] + 0.001, 0.10) == 0.0  # no holes far out
    kept = out > 0
    assert np.array_equal(out[kept], z[kept])


def test_depth_dropouts_stay_put_frame_to_frame():
    z = ramp_depth()
    field = effects.scene_field(3, "depth_dropouts", z.shape, D405_DROPOUTS["blob_px"])
    a, b = (
        effects.depth_dropouts(z, D405_DROPOUTS, effects.effect_rng(3, "d", k), 0.0, field=field)
        for k in (1, 2)
    )
    ha, hb = a == 0, b == 0
    iou = (ha & hb).sum() / (ha | hb).sum()
    assert 0.85 < iou < 1.0  # the same holes, their edges flicker


JUMPS = EFFECT_DEFAULTS["depth_jumps"]


def holed_plane() -> np.ndarray:
    """A plane at 80 mm with a 60 x 60 px hole in the middle."""
    z = np.full((200, 200), 0.08, np.float32)
    z[70:130, 70:130] = 0.0
    return z


def test_depth_jumps_read_behind_the_surface_at_hole_edges():
    z = holed_plane()
    p = dict(JUMPS, rate=0.3)
    out = effects.depth_jumps(z, p, effects.effect_rng(0, "depth_jumps", 5), 0.0)
    changed = out != z
    assert changed.any()
    # Only in the band around the hole's edge, on both sides, mostly inside the hole.
    ys, xs = np.nonzero(changed)
    ring = np.maximum(np.abs(ys - 99.5), np.abs(xs - 99.5))
    assert ring.min() >= 30 - p["edge_px"] - 1 and ring.max() <= 30 + p["edge_px"] + 1
    assert (z[changed] == 0).mean() > 0.7
    excess = out[changed] - 0.08
    assert np.abs(excess).max() <= p["max_m"] + 1e-6
    assert 0.3 * p["scale_m"] < np.median(np.abs(excess)) < 1.5 * p["scale_m"]
    assert abs((excess > 0).mean() - p["behind_share"]) < 0.1  # most read behind


def test_depth_jumps_need_holes_and_a_rate():
    full = np.full((100, 100), 0.08, np.float32)
    rng = effects.effect_rng(0, "depth_jumps", 1)
    assert np.array_equal(effects.depth_jumps(full, dict(JUMPS), rng, 0.0), full)
    z = holed_plane()
    assert np.array_equal(effects.depth_jumps(z, dict(JUMPS, rate=0.0), rng, 0.0), z)


def test_depth_jumps_change_only_depth_and_are_seeded(base):
    eff = '["depth_dropouts", "depth_jumps"]'
    holes = images(run('["depth_dropouts"]')[1])
    a, b, c = (images(run(eff, seed=s)[1]) for s in (0, 0, 1))
    assert np.array_equal(a[0], base[0]) and np.array_equal(a[2], base[2])
    assert not np.array_equal(a[1], holes[1])  # it ran, on the depth
    assert np.array_equal(a[1], b[1]) and not np.array_equal(a[1], c[1])


def test_rgb_noise_is_a_demosaiced_mosaics_noise():
    # On a flat image: each pixel's noise is shared with its neighbours both ways (the D405:
    # 0.2 on its textured membrane, more on flat areas) and with its other channels (0.4-0.6):
    # white noise has neither, the former model had no vertical correlation.
    rgb = np.full((300, 300, 3), 128, np.uint8)
    p = effects_defaults("rgb_noise")
    d = effects.rgb_noise(rgb, p, np.random.default_rng(0), 0.0).astype(float) - 128
    sd = d.std(axis=(0, 1))
    assert abs(d.mean()) < 0.1
    assert np.all((0.45 * p["sigma"] < sd) & (sd < 0.8 * p["sigma"]))
    assert 0.4 < np.corrcoef(d[..., 0].ravel(), d[..., 1].ravel())[0, 1] < 0.8
    for c in range(3):
        h = np.corrcoef(d[:, :-1, c].ravel(), d[:, 1:, c].ravel())[0, 1]
        v = np.corrcoef(d[:-1, :, c].ravel(), d[1:, :, c].ravel())[0, 1]
        assert 0.3 < h < 0.65 and 0.3 < v < 0.65


def test_rgb_noise_is_stronger_on_edges_than_on_flat_areas():
    # The denoiser smooths flat areas and keeps edges: the D405's grey noise is 1.7x stronger
    # on edges than on flat areas (docs/sim-noise.md), and the optical flow reads the edges.
    img = np.full((200, 200, 3), 60, np.uint8)
    img[:, (np.arange(200) // 8) % 2 == 1] = 160
    p = effects_defaults("rgb_noise")
    rng = np.random.default_rng(1)
    out = np.stack([effects.rgb_noise(img, p, rng, 0.0).astype(float) for _ in range(30)])
    sd = out.std(axis=0).mean(axis=2)
    x = np.arange(200) % 8
    mid = (x == 3) | (x == 4)
    assert sd[:, (x == 0) | (x == 7)].mean() > 1.3 * sd[:, mid].mean()
    assert np.abs(out.mean(axis=0) - img).mean() < 3.0  # the mosaic keeps the image
    raw = effects.rgb_noise(img, dict(p, denoise_levels=0.0), rng, 0.0).astype(float) - img
    assert raw[:, mid].std() > 1.3 * sd[:, mid].mean()  # without the denoiser, no such gap


def test_rgb_noise_on_a_grey_image():
    grey = np.full((100, 100), 128, np.uint8)
    out = effects.rgb_noise(grey, effects_defaults("rgb_noise"), np.random.default_rng(0), 0.0)
    assert out.shape == grey.shape and out.dtype == np.uint8
    assert 0.5 < (out.astype(float) - 128).std() < 4.0


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 2, 3), (3, 5, 3), (61, 81, 3)])
def test_rgb_noise_keeps_odd_and_tiny_images(shape):
    # The mosaic has a 2 x 2 period: an odd or one-pixel image must come back whole, black
    # and white ones saturated, not wrapped.
    p = effects_defaults("rgb_noise")
    for level in (0, 255):
        img = np.full(shape, level, np.uint8)
        out = effects.rgb_noise(img, p, np.random.default_rng(0), 0.0)
        assert out.shape == img.shape and out.dtype == np.uint8
        assert np.abs(out.astype(int) - level).mean() < p["sigma"]
