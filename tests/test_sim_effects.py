"""Effects: an unnamed effect costs nothing; a named one changes only its own output."""

from __future__ import annotations

import numpy as np
import pytest
from _sim_fake import FakePhysics, small_scene
from bubble_rt.sim import effects
from bubble_rt.sim.simulator import Simulator


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
    rgb, depth, p, _ = images(run('["depth_dropouts"]')[1])
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
    d = rgb.astype(float) - base[0].astype(float)
    assert 1.5 < d[base[1] > 0].std() < 2.5


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
