"""Daemon configuration: defaults round-trip through TOML, errors name the key."""

from __future__ import annotations

import pytest
from bubble_rt.config import ConfigError, DaemonConfig


def test_defaults_round_trip_through_toml(tmp_path):
    cfg = DaemonConfig()
    p = tmp_path / "c.toml"
    p.write_text(cfg.to_toml())
    assert DaemonConfig.load(p) == cfg


def test_defaults_match_the_issue():
    cfg = DaemonConfig()
    assert cfg.camera.source == "sim" and cfg.pressure.source == "camera"
    assert cfg.network.pub == "tcp://127.0.0.1:5555"
    assert cfg.network.control == "tcp://127.0.0.1:5556"
    assert cfg.pressure.baud == 115200
    assert cfg.estimator.kind == "fem" and cfg.estimator.mesh == "medium"


def test_empty_file_is_valid(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("")
    assert DaemonConfig.load(p) == DaemonConfig()


def test_partial_file_keeps_other_defaults(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('sensor_id = "left"\n[estimator]\nk_f = 0.5\n')
    cfg = DaemonConfig.load(p)
    assert cfg.sensor_id == "left" and cfg.estimator.k_f == 0.5
    assert cfg.estimator.k_u == DaemonConfig().estimator.k_u


def test_int_accepted_for_float():
    cfg = DaemonConfig.from_dict({"estimator": {"youngs_modulus": 1000000}})
    assert cfg.estimator.youngs_modulus == 1e6 and isinstance(cfg.estimator.youngs_modulus, float)


def _err(data) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        DaemonConfig.from_dict(data)
    return ei.value


def test_unknown_key_is_named():
    e = _err({"camera": {"sorce": "sim"}})
    assert e.key == "camera.sorce" and "unknown key" in str(e)


def test_unknown_section_is_named():
    assert _err({"cameras": {}}).key == "cameras"


def test_wrong_type_is_named():
    e = _err({"pressure": {"baud": "fast"}})
    assert e.key == "pressure.baud" and "expected int" in str(e)


def test_bool_is_not_a_number():
    assert _err({"estimator": {"k_f": True}}).key == "estimator.k_f"


def test_negative_k_f_is_named():
    e = _err({"estimator": {"k_f": -1.0}})
    assert str(e).startswith("estimator.k_f:")


def test_unknown_camera_source_is_named():
    assert _err({"camera": {"source": "webcam"}}).key == "camera.source"


def test_replay_needs_a_path():
    assert "replay needs a path" in str(_err({"camera": {"source": "replay"}}))


def test_serial_needs_a_port():
    assert _err({"pressure": {"source": "serial"}}).key == "pressure.source"


def test_constant_pressure_must_be_a_number():
    assert _err({"pressure": {"source": "constant:abc"}}).key == "pressure.source"


def test_missing_mesh_file_is_named():
    e = _err({"estimator": {"mesh": "/nonexistent/mesh.vtk"}})
    assert e.key == "estimator.mesh"


def test_bad_address_is_named():
    assert _err({"network": {"pub": "localhost:5555"}}).key == "network.pub"


def test_same_pub_and_control_is_an_error():
    e = _err({"network": {"pub": "tcp://127.0.0.1:1", "control": "tcp://127.0.0.1:1"}})
    assert e.key == "network.control"


def test_sensor_id_must_be_topic_safe():
    assert _err({"sensor_id": "a b"}).key == "sensor_id"


def test_min_above_max_pressure():
    assert _err({"pressure": {"min_pa": 3e5}}).key == "pressure.max_pa"


def test_invalid_toml_is_reported(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[camera\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        DaemonConfig.load(p)


def test_with_overrides_skips_none():
    cfg = DaemonConfig().with_overrides(**{"camera.source": None, "estimator.mesh": "coarse"})
    assert cfg.camera.source == "sim" and cfg.estimator.mesh == "coarse"


def test_config_dump_command_prints_defaults(capsys):
    import tomllib

    from bubble_rt.cli import main

    assert main(["config", "dump"]) == 0
    out = capsys.readouterr().out
    assert DaemonConfig.from_dict(tomllib.loads(out)) == DaemonConfig()


def test_config_check_command_names_key(tmp_path, capsys):
    from bubble_rt.cli import main

    p = tmp_path / "c.toml"
    p.write_text("[flow]\nmethod = 'magic'\n")
    assert main(["config", "check", str(p)]) == 2
    assert "flow.method" in capsys.readouterr().err


def test_estimator_section_defaults_are_the_estimators():
    """`[estimator]` defaults must be EstimatorConfig's: the daemon, `estimate` and `eval` all
    run the same default estimator."""
    from bubble_rt.config import DaemonConfig
    from bubble_rt.estimation.estimator import CONFIG_KEYS, EstimatorConfig

    section, est = DaemonConfig().estimator, EstimatorConfig()
    for key, (name, sub) in CONFIG_KEYS.items():
        value = getattr(est, name) if sub is None else getattr(getattr(est, name), sub)
        if key == "ambient_pa":
            # 0 in the file means "the sensor profile's"; on simulated data that is the default.
            assert section.ambient_pa == 0.0
            assert section.sensor_profile("sim").ambient_pa == value
            continue
        assert getattr(section, key) == value, key


def test_profile_follows_the_data_layout_unless_named():
    """Punyo recordings, ROS 2 bags and RealSense cameras are Punyo hardware; the rest is the
    simulator's bubble; a named profile wins, and an explicit ambient pressure wins over both."""
    from bubble_rt.config import DaemonConfig
    from bubble_rt.estimation.pipeline import capture_settings
    from bubble_rt.sensor import PUNYO, SIM

    section = DaemonConfig().estimator
    for layout in ("punyo", "rosbag", "realsense"):
        assert section.sensor_profile(layout) is PUNYO
    for layout in ("sim", "png", "mcap", ""):
        assert section.sensor_profile(layout) is SIM
    named = DaemonConfig().with_overrides(**{"estimator.profile": "sim"})
    assert named.estimator.sensor_profile("punyo") is SIM
    assert PUNYO.ambient_pa != SIM.ambient_pa
    ambient = {
        layout: capture_settings(DaemonConfig(), realtime=False, layout=layout)["config"].ambient_pa
        for layout in ("punyo", "sim")
    }
    assert ambient == {"punyo": PUNYO.ambient_pa, "sim": SIM.ambient_pa}
    pinned = DaemonConfig().with_overrides(**{"estimator.ambient_pa": 99000.0})
    assert capture_settings(pinned, realtime=False, layout="punyo")["config"].ambient_pa == 99000.0


@pytest.mark.parametrize("value", [130_000.0, -5.0])
def test_ambient_pressure_out_of_range_names_the_key(value):
    from bubble_rt.config import ConfigError, DaemonConfig

    with pytest.raises(ConfigError, match="estimator.ambient_pa"):
        DaemonConfig().with_overrides(**{"estimator.ambient_pa": value})
