"""Scenes (TOML), trajectories and the dataset procedure."""

from __future__ import annotations

import numpy as np
import pytest
from _sim_fake import FakeSphere, small_scene
from bubble_rt.mesh import Mesh
from bubble_rt.sim.dataset import DatasetSettings, dataset_scenes
from bubble_rt.sim.scene import SceneError, builtin_scenes, load_scene, parse_scene
from bubble_rt.sim.trajectory import ReferenceSurface, trajectory_poses

BASE = """
[trajectory]
keyframes = [ { t = 0.0, at = [0.0, 0.0], depth = -0.002 }, { t = 1.0, at = [0.0, 0.0], depth = 0.004 } ]
"""


def test_builtin_scenes_load():
    assert {"demo", "clean", "oracle"} <= set(builtin_scenes())
    demo = load_scene("demo")
    assert demo.indenter.preset == "round"
    assert demo.trajectory.loop
    assert demo.frames == 120
    assert demo.has("friction") and demo.params("friction")["mu"] == 0.5
    assert demo.sensor.camera == "d405" and demo.rates.pressure_hz == 100.0
    oracle = load_scene("oracle")
    assert oracle.has("oracle") and oracle.physics_key("0") == demo.physics_key("0")
    assert load_scene("clean").effects == ()


def test_frames_default_to_trajectory_length():
    assert parse_scene(BASE).frames == 31


def test_scene_file_path_loads(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text('seed = 3\neffects = ["rgb_noise"]\n' + BASE)
    s = load_scene(p)
    assert s.name == "mine" and s.seed == 3 and s.effect_names == ("rgb_noise",)


def test_effect_parameters_override_defaults():
    s = parse_scene("[effects]\ndepth_noise = { sigma_per_m2 = 0.5 }\n" + BASE)
    from bubble_rt.sim.effect_names import EFFECT_DEFAULTS

    assert s.params("depth_noise") == {**EFFECT_DEFAULTS["depth_noise"], "sigma_per_m2": 0.5}


def test_user_indenter_shapes_parse():
    s = parse_scene(
        """
[indenter]
shapes = [ { type = "sphere", radius = 0.01 },
           { type = "capsule", radius = 0.004, length = 0.02, center = [0, 0, 0.01] },
           { type = "box", size = [0.01, 0.01, 0.02] } ]
"""
        + BASE
    )
    assert s.indenter.preset is None
    assert [x.type for x in s.indenter.shapes] == ["sphere", "capsule", "box"]
    assert s.indenter.shapes[1].length == 0.02


def expect_error(text: str, key: str) -> None:
    with pytest.raises(SceneError) as exc:
        parse_scene(text)
    assert str(exc.value).startswith(key), str(exc.value)


def test_error_names_unknown_effect():
    expect_error('effects = ["sparkles"]\n' + BASE, "effects.sparkles")


def test_error_names_unknown_effect_parameter():
    expect_error("[effects]\nrgb_noise = { sigm = 2 }\n" + BASE, "effects.rgb_noise.sigm")


def test_error_names_missing_trajectory():
    expect_error("seed = 1\n", "trajectory")


def test_error_names_bad_keyframe_depth():
    expect_error(BASE.replace("depth = 0.004", 'depth = "deep"'), "trajectory.keyframes[1].depth")


def test_error_names_non_increasing_keyframe_time():
    expect_error(BASE.replace("t = 1.0", "t = 0.0"), "trajectory.keyframes[1].t")


def test_error_names_unknown_camera():
    expect_error('[sensor]\ncamera = "kinect"\n' + BASE, "sensor.camera")


def test_error_names_too_few_sim_nodes():
    expect_error("[sensor]\nsim_nodes = 5\n" + BASE, "sensor.sim_nodes")


def test_error_names_unknown_texture():
    expect_error('[sensor]\ntexture = "plaid"\n' + BASE, "sensor.texture")
    expect_error("[sensor]\ntexture = [1]\n" + BASE, "sensor.texture")
    assert parse_scene('[sensor]\ntexture = "punyo"\n' + BASE).sensor.texture == "punyo"


def test_error_names_unknown_physics_key():
    expect_error("[physics]\nstiffness = 3\n" + BASE, "physics.stiffness")


def test_error_names_negative_pressure():
    expect_error("[physics]\ngauge_pressure_pa = -1.0\n" + BASE, "physics.gauge_pressure_pa")


def test_error_names_bad_shape_radius():
    expect_error(
        '[indenter]\nshapes = [ { type = "sphere", radius = 0 } ]\n' + BASE,
        "indenter.shapes[0].radius",
    )


def test_error_names_unknown_indenter_preset():
    expect_error('[indenter]\npreset = "spoon"\n' + BASE, "indenter.preset")


def test_error_names_oracle_with_image_effects():
    expect_error('effects = ["oracle", "rgb_noise"]\n' + BASE, "effects")


def test_error_names_invalid_toml():
    expect_error("seed = = 1\n", "scene is not valid TOML")


def test_physics_key_ignores_sensor_noise_but_not_friction():
    a = parse_scene(BASE)
    b = parse_scene('effects = ["rgb_noise", "depth_noise"]\n' + BASE)
    c = parse_scene('effects = ["friction"]\n' + BASE)
    assert a.physics_key("0") == b.physics_key("0")
    assert a.physics_key("0") != c.physics_key("0")
    assert a.physics_key("0") != a.physics_key("1")  # package version is part of the key


def test_physics_key_changes_with_the_physics_revision(monkeypatch):
    import bubble_rt.sim.physics as physics

    a = parse_scene(BASE).physics_key("0")
    monkeypatch.setattr(physics, "PHYSICS_REVISION", physics.PHYSICS_REVISION + 1)
    assert parse_scene(BASE).physics_key("0") != a


def test_surface_keyframes_touch_at_zero_depth_and_press_by_depth():
    m = Mesh.generate(600)
    surf = ReferenceSurface(m.vertices, m.triangles)
    ball = FakeSphere(0.01)
    s = small_scene(frames=4)
    poses = trajectory_poses(s.trajectory, 4, 30.0, surf, ball.distance)
    dense = Mesh.generate(3000).vertices  # the same dome, finer: measures the true penetration
    first = ball.distance(dense, poses[0]).min()
    last = ball.distance(dense, poses[-1]).min()
    assert abs(first - 0.002) < 2e-4  # starts 2 mm away
    assert abs(last + 0.006) < 5e-4  # ends 6 mm deep


def test_dataset_is_reproducible_and_seeded():
    a = dataset_scenes(DatasetSettings(per_indenter=4, seed=7))
    b = dataset_scenes(DatasetSettings(per_indenter=4, seed=7))
    c = dataset_scenes(DatasetSettings(per_indenter=4, seed=8))
    assert a == b
    assert a != c
    assert [s.indenter.preset for s in a[::4]] == ["round", "point", "line", "square", "split"]


def test_dataset_trajectories_go_free_near_contact_with_fixed_orientation():
    st = DatasetSettings(per_indenter=6, seed=1)
    for s in dataset_scenes(st):
        k = s.trajectory.keyframes
        assert k[0].depth < -0.009 and -0.0031 < k[1].depth < 0 and k[2].depth > 0
        assert len({kf.approach for kf in k}) == 1 and len({kf.spin_deg for kf in k}) == 1
        n = np.asarray(k[0].approach)
        assert n[2] < -0.5  # roughly facing the dome from above
        assert s.frames == st.frames


def test_dataset_has_light_and_heavy_touches():
    st = DatasetSettings(per_indenter=4, seed=3)
    table = dict(st.depths)
    scenes = dataset_scenes(st)
    light = [s.trajectory.keyframes[2].depth <= table[s.indenter.preset][0][1] for s in scenes]
    heavy = [s.trajectory.keyframes[2].depth >= table[s.indenter.preset][1][0] for s in scenes]
    assert sum(light) == 10 and sum(heavy) == 10


def test_user_shapes_become_physics_indenters():
    from bubble_rt.sim.simulator import DefaultPhysics

    s = parse_scene(
        """
[indenter]
shapes = [ { type = "sphere", radius = 0.01, center = [0, 0, 0.01] },
           { type = "capsule", radius = 0.002, length = 0.02, center = [0, 0, 0.03], axis = [0, 0, 1] },
           { type = "box", size = [0.04, 0.01, 0.01], center = [0, 0, 0.05] } ]
"""
        + BASE
    )
    phys = DefaultPhysics()
    ind = phys.indenter(s.indenter)
    pts = np.array([[0.0, 0.0, -0.005], [0.0, 0.0, 0.0], [0.019, 0.0, 0.05], [0.0, 0.0, 0.1]])
    d = phys.distance(ind, pts, np.eye(4))
    np.testing.assert_allclose(d[:3], [0.005, 0.0, -0.001], atol=1e-9)
    assert d[3] > 0.04
    assert phys.distance(phys.indenter(load_scene("demo").indenter), pts[:1], np.eye(4))[0] > 0


def test_default_physics_is_the_sim_profiles_bubble_and_keeps_its_cache_key():
    """The default scene's physics is declared once, in bubble_rt.sensor; a field added since
    (the stress-free dome) stays out of the key at its default, so existing caches stay valid,
    and enters it when set."""
    from dataclasses import asdict

    from bubble_rt.sensor import SIM_BUBBLE
    from bubble_rt.sim.scene import PhysicsSpec

    demo = load_scene("demo")
    assert demo.profile == "sim" and demo.physics == PhysicsSpec.of(SIM_BUBBLE)
    assert demo.sensor.camera_pose is None
    legacy = asdict(demo.physics)
    del legacy["rest_dome_height_m"]
    import hashlib
    import json

    from bubble_rt.sim.physics import PHYSICS_REVISION

    payload = {
        "version": "0",
        "physics_revision": PHYSICS_REVISION,
        "sim_nodes": demo.sensor.sim_nodes,
        "physics": legacy,
        "indenter": asdict(demo.indenter),
        "trajectory": asdict(demo.trajectory),
        "frames": demo.frames,
        "camera_hz": demo.rates.camera_hz,
        "friction": demo.params("friction"),
        "gas": True,
    }
    blob = json.dumps(payload, sort_keys=True, default=str).encode()
    assert demo.physics_key("0") == hashlib.sha256(blob).hexdigest()[:32]
    taller = parse_scene("[physics]\nrest_dome_height_m = 0.025\n" + BASE)
    assert taller.physics_key("0") != parse_scene(BASE).physics_key("0")


def test_profile_sets_physics_and_camera_defaults():
    from bubble_rt.sensor import PUNYO_BUBBLE

    s = parse_scene('profile = "punyo"\n[physics]\nchamber_volume_m3 = 2e-4\n' + BASE)
    assert s.profile == "punyo"
    assert s.physics.gauge_pressure_pa == PUNYO_BUBBLE.gauge_pressure_pa
    assert s.physics.rest_dome_height_m == PUNYO_BUBBLE.rest_dome_height_m
    assert s.physics.chamber_volume_m3 == 2e-4  # a key still overrides the profile
    assert s.sensor.camera_pose == PUNYO_BUBBLE.camera_pose
    assert s.sensor.texture == "punyo" and parse_scene(BASE).sensor.texture == "dots"
    with pytest.raises(SceneError, match="profile: unknown sensor profile 'gel'"):
        parse_scene('profile = "gel"\n' + BASE)
    with pytest.raises(SceneError, match="profile: unknown sensor profile"):
        parse_scene("profile = [1]\n" + BASE)
