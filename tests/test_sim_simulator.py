"""The simulator end to end (fake physics here; real physics at the end), cache and CLI."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from _sim_fake import FakePhysics, small_scene
from bubble_rt.sim import cache
from bubble_rt.sim.simulator import Simulator
from waiting import wait_for


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))


def test_frames_carry_images_pressure_times_and_truth():
    sim = Simulator(small_scene(frames=8), physics=FakePhysics())
    frames = list(sim.frames())
    assert len(frames) == 8
    f = frames[-1]
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    assert np.diff([x.t for x in frames]).min() == pytest.approx(1 / 30)
    assert f.truth.contact.any() and f.truth.net_force[2] < 0
    assert f.pressure_pa > 101325.0
    assert f.t_pressure <= f.t and f.t - f.t_pressure < 0.01 + 1e-12
    assert sim.camera.width == 640


def test_pressure_stream_runs_at_its_own_rate():
    sim = Simulator(small_scene(frames=31), physics=FakePhysics())
    r = sim.pressure_readings()
    assert np.allclose(np.diff(r.t), 0.01)
    assert len(r.t) == 101
    np.testing.assert_allclose(r.pressure_hpa, r.pressure_pa / 100)


def test_physics_is_cached_on_disk_and_keyed_by_content():
    fake = FakePhysics()
    scene = small_scene(frames=3)
    _ = Simulator(scene, physics=fake).run
    assert fake.calls == 1
    assert cache.cache_path(Simulator(scene).physics_key()).exists()
    again = Simulator(scene, physics=fake)
    list(again.frames())
    assert fake.calls == 1  # served from the cache
    _ = Simulator(small_scene(frames=4), physics=fake).run
    assert fake.calls == 2


def test_physics_progress_counts_up_once_when_two_threads_ask_at_once():
    """The first run's progress counted backwards (71, 73, 84, 83, ...): the daemon's reference
    capture and its camera thread each computed the physics and reported their own counts."""
    fake = FakePhysics()
    reports: list[tuple[int, int]] = []
    second_asks = threading.Event()

    def progress(done: int, total: int) -> None:
        reports.append((done, total))
        if done == 1:  # the other thread asks while the physics is being computed
            second_asks.wait(10)

    sim = Simulator(small_scene(frames=20), physics=fake, use_cache=False, progress=progress)
    runs: list = []
    first = threading.Thread(target=lambda: runs.append(sim.run))
    first.start()
    assert wait_for(lambda: reports, 30)
    second = threading.Thread(target=lambda: (second_asks.set(), runs.append(sim.run)))
    second.start()
    first.join(30)
    second.join(30)
    assert fake.calls == 1, "the physics was computed once"
    assert [d for d, _ in reports] == list(range(1, 21)) and {t for _, t in reports} == {20}
    assert len(runs) == 2 and runs[0] is runs[1]


def test_progress_bar_never_counts_back(monkeypatch):
    import io

    import tqdm
    from bubble_rt.sim.simulator import progress_bar

    counts: list[int] = []

    class Bar(tqdm.tqdm):  # type: ignore[type-arg]
        def update(self, n: float | None = 1) -> bool | None:
            out = super().update(n)
            counts.append(int(self.n))
            return out

    monkeypatch.setattr(tqdm, "tqdm", Bar)
    report = progress_bar("physics", file=io.StringIO())
    for done in (1, 71, 73, 84, 83, 90, 2, 100):  # reports out of order
        report(done, 100)
    assert counts == [1, 71, 73, 84, 90, 100]


def test_same_scene_and_seed_give_identical_output():
    eff = '["depth_noise", "depth_dropouts", "rgb_noise", "pressure_noise", "timestamp_jitter"]'
    a = list(Simulator(small_scene(eff), physics=FakePhysics(), use_cache=False).frames())
    b = list(Simulator(small_scene(eff), physics=FakePhysics(), use_cache=False).frames())
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.rgb, y.rgb) and np.array_equal(x.depth, y.depth)
        assert x.pressure_pa == y.pressure_pa and x.t == y.t
        assert np.array_equal(x.truth.net_force, y.truth.net_force)


def test_reference_frames_are_untouched():
    sim = Simulator(small_scene(), physics=FakePhysics())
    ref = sim.reference_frames(3)
    assert len(ref) == 3 and all(f.t < 0 for f in ref)
    assert all(not f.truth.contact.any() for f in ref)
    assert np.array_equal(ref[0].truth.net_force, np.zeros(3))
    assert np.array_equal(ref[0].depth, ref[1].depth)  # no noise named: identical


def test_looping_keeps_time_increasing():
    sim = Simulator(small_scene(frames=3), physics=FakePhysics())
    it = sim.frames(loop=True)
    frames = [next(it) for _ in range(7)]
    assert [f.index for f in frames] == list(range(7))
    assert np.all(np.diff([f.t for f in frames]) > 0)
    assert np.array_equal(frames[0].depth, frames[3].depth)


def test_simulate_cli_writes_the_documented_layout(tmp_path, monkeypatch):
    from bubble_rt.cli import main
    from bubble_rt.sim import simulator

    monkeypatch.setattr(simulator, "DefaultPhysics", FakePhysics)
    scene = tmp_path / "s.toml"
    from bubble_rt.sim.scene import parse_scene  # noqa: F401

    scene.write_text(
        'effects = ["pressure_noise"]\n[sensor]\nsim_nodes = 300\n[trajectory]\nkeyframes = ['
        "{ t = 0.0, at = [0.0, 0.0], depth = -0.002 }, { t = 0.1, at = [0.0, 0.0], depth = 0.004 }]\n"
    )
    out = tmp_path / "rec.npz"
    assert main(["simulate", str(scene), "-o", str(out), "--frames", "5", "--seed", "3"]) == 0
    z = np.load(out)
    assert str(z["format"]) == "bubble_rt.sim.npz/1"
    assert z["rgb"].shape == (5, 480, 640, 3) and z["depth"].shape == (5, 480, 640)
    assert z["truth_net_force"].shape == (5, 3) and z["reference_rgb"].shape[0] == 5
    assert z["truth_node_forces"].shape[1] == z["sim_reference_vertices"].shape[0]
    assert len(z["pressure_stream_t"]) > len(z["t"])
    assert '"seed": 3' in str(z["scene_json"])
    from bubble_rt.commands.simulate import load_recording

    cam, frames, reference = load_recording(out)
    assert cam.width == 640 and len(frames) == 5 and len(reference) == 5
    assert np.array_equal(frames[-1].rgb, z["rgb"][-1])
    assert np.array_equal(frames[-1].truth.net_force, z["truth_net_force"][-1])
    g = frames[-1].truth
    np.testing.assert_allclose(g.displace(g.sim_reference_vertices), g.sim_vertices, atol=1e-12)


def test_simulate_cli_reports_scene_errors(tmp_path, capsys):
    from bubble_rt.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text("seed = 1\n")
    assert main(["simulate", str(bad), "-o", str(tmp_path / "x.npz")]) == 2
    assert "trajectory: missing" in capsys.readouterr().err


# ---------------------------------------------------------------------- real physics
def test_demo_scene_runs_end_to_end_with_the_real_physics():
    from bubble_rt.sim.scene import SensorSpec, load_scene

    scene = load_scene("demo").with_changes(frames=22, sensor=SensorSpec(sim_nodes=500))
    sim = Simulator(scene)
    frames = list(sim.frames())
    assert len(frames) == 22
    assert all(f.truth.converged for f in frames)
    first, pressed = frames[0], frames[-1]  # 0.7 s: pressed ~6.5 mm at the dome top
    assert not first.truth.contact.any() and np.allclose(first.truth.net_force, 0)
    f = pressed.truth.net_force
    assert f[2] < -1.0 and abs(f[2]) > 5 * np.hypot(f[0], f[1])  # down, along the axis
    assert pressed.truth.pressure_pa > first.truth.pressure_pa  # the air is sealed
    # The dome top comes towards the camera where it is pressed.
    c = np.s_[230:250, 300:320]
    d0, d1 = first.depth[c], pressed.depth[c]
    assert np.median(d1[d1 > 0]) < np.median(d0[d0 > 0]) - 0.003
    ref = sim.reference_frames(2)
    assert ref[0].truth.pressure_pa == pytest.approx(101325.0 + 5000.0, rel=1e-6)


def test_real_physics_same_scene_same_output():
    scene = small_scene('["friction", "gas_compression", "rgb_noise"]', frames=4, nodes=300)
    a = list(Simulator(scene, use_cache=False).frames())
    b = list(Simulator(scene, use_cache=False).frames())
    assert a[-1].truth.contact.any()
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.truth.sim_vertices, y.truth.sim_vertices)
        assert np.array_equal(x.rgb, y.rgb) and x.pressure_pa == y.pressure_pa


def test_dataset_has_light_and_heavy_touches_in_the_physics():
    from bubble_rt.sim.dataset import DatasetSettings, dataset_scenes

    st = DatasetSettings(per_indenter=2, frames=20, indenters=("round",), sim_nodes=600, seed=0)
    light, heavy = dataset_scenes(st)
    f_light = np.linalg.norm(list(Simulator(light).frames())[-1].truth.net_force)
    f_heavy = np.linalg.norm(list(Simulator(heavy).frames())[-1].truth.net_force)
    assert 0.4 < f_light < 2.5
    assert f_heavy >= 10.0
