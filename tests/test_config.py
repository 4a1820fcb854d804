"""Daemon configuration: defaults round-trip through TOML, errors name the key."""

from __future__ import annotations

import math
import tomllib
from typing import Any

import pytest
from bubble_rt.config import (
    ESTIMATOR_RANGES,
    ConfigError,
    DaemonConfig,
    dump_toml,
    key_choices,
    key_comment,
    key_range,
    keys,
)
from bubble_rt.io.protocol import PARAM_NAMES
from daemon_fakes import nested, refused_at_load


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


# ------------------------------------------------------------------------------ fuzz
HUGE_INT = 10**12


FUZZ_VALUES: list[Any] = [
    "wrong type",
    True,
    math.nan,
    math.inf,
    -math.inf,
    -1,
    -1.0,
    0,
    0.0,
    1e300,
    -1e300,
    HUGE_INT,
    5e-324,
]


#: Checks between keys (the other key keeps its default).
CROSS_CHECKS = {
    "pressure.min_pa": lambda v: v < DaemonConfig().pressure.max_pa,
    "pressure.max_pa": lambda v: v > DaemonConfig().pressure.min_pa,
}


def _expected_valid(f: Any, value: Any, dotted: str = "") -> bool | None:
    """What the fuzz test expects of ``value`` for key ``dotted`` (from its declaration)."""
    default = f.default
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, str):
        # Numbers are the wrong type; words: only the declared choices (free-form words such
        # as paths and sources have their own named tests).
        if not isinstance(value, str):
            return False
        choices = key_choices(f)
        return None if choices is None else value in choices
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if isinstance(default, int) and not isinstance(value, int):
        return False
    rng = key_range(f)
    assert rng is not None, "every numeric key has a range"
    ok = math.isfinite(value) and rng.lo <= value <= rng.hi
    return ok and CROSS_CHECKS.get(dotted, lambda v: True)(value)


def _mid_value(f: Any) -> Any:
    rng = key_range(f)
    v = math.sqrt(max(rng.lo, 1e-3) * rng.hi) if rng.lo >= 0 else (rng.lo + rng.hi) / 2
    return int(v) if isinstance(f.default, int) else v


def test_config_fuzz_every_key_refused_at_load_with_its_key_named_or_accepted():
    all_keys = keys()
    assert len(all_keys) >= 45  # enumerated from the dataclasses: a new key cannot be missed
    checked = 0
    for dotted, f in all_keys:
        values = list(FUZZ_VALUES)
        if key_range(f) is not None:
            values.append(_mid_value(f))
        if key_choices(f) is not None:
            values.append("not-a-choice")
        for value in values:
            valid = _expected_valid(f, value, dotted)
            if valid is None:
                continue
            if valid:
                cfg = DaemonConfig.from_dict(nested(dotted, value))
                got = cfg
                for part in dotted.split("."):
                    got = getattr(got, part)
                assert got == value, (dotted, value)
            else:
                e = refused_at_load(dotted, value)
                assert e.key == dotted, (dotted, value, str(e))
                rng = key_range(f)
                if rng is not None:
                    assert rng.text() in str(e), (dotted, value, str(e))
                if isinstance(value, float) and not isinstance(f.default, str):
                    assert repr(value) in str(e), (dotted, value, str(e))
            checked += 1
    assert checked > 500


def test_config_fuzz_through_toml_files(tmp_path):
    """The same refusals when the values come from a file (nan/inf are TOML floats)."""
    p = tmp_path / "c.toml"
    for dotted, f in keys():
        section, _, name = dotted.rpartition(".")
        for text in ("nan", "inf", "-1", "1e300"):
            p.write_text((f"[{section}]\n" if section else "") + f"{name} = {text}\n")
            value = tomllib.loads(p.read_text())
            value = value[section][name] if section else value[name]
            if _expected_valid(f, value, dotted):
                DaemonConfig.load(p)
                continue
            with pytest.raises(ConfigError) as ei:
                DaemonConfig.load(p)
            assert ei.value.key == dotted, (dotted, text, str(ei.value))


def test_every_key_has_a_documented_range_in_config_dump():
    out = dump_toml(DaemonConfig())
    assert DaemonConfig.from_dict(tomllib.loads(out)) == DaemonConfig()
    for dotted, f in keys():
        assert f.metadata.get("doc"), f"{dotted} has no documentation"
        comment = key_comment(f)
        first = comment.split()[0]
        assert first in out, dotted
        rng = key_range(f)
        if rng is not None:
            assert rng.text() in " ".join(out.split()), dotted
        if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            assert rng is not None, f"numeric {dotted} has no range"


# ------------------------------------------------------------------------------ the issue's runs
def test_constant_nan_pressure_is_refused_at_load():
    e = refused_at_load("pressure.source", "constant:nan")
    assert e.key == "pressure.source"
    assert "nan" in str(e) and "[30000, 200000]" in str(e)
    e = refused_at_load("pressure.source", "constant:1e300")
    assert "1e+300" in str(e)
    DaemonConfig.from_dict(nested("pressure.source", "constant:101325"))


def test_huge_thickness_is_refused_at_load():
    e = refused_at_load("estimator.thickness", 1e300)
    assert e.key == "estimator.thickness" and "[1e-05, 0.01] m" in str(e) and "1e+300" in str(e)


def test_opencv_threads_are_bounded():
    e = refused_at_load("processing.opencv_threads", 100000000000)
    assert e.key == "processing.opencv_threads" and "[0, 256]" in str(e)
    assert "100000000000" in str(e)


def test_parameter_ranges_are_the_configurations():
    for name in PARAM_NAMES:
        r = ESTIMATOR_RANGES[name]
        for bad in (r.lo - abs(r.lo) - 1, r.hi * 10):
            with pytest.raises(ConfigError, match=f"estimator.{name}: must be in"):
                DaemonConfig.from_dict({"estimator": {name: bad}})
            from bubble_rt.daemon.control import validate_params

            assert validate_params({name: bad}) == (f"set_params: {name} {r.problem(bad)}")
        DaemonConfig.from_dict({"estimator": {name: r.lo}})
        DaemonConfig.from_dict({"estimator": {name: r.hi}})


def test_flow_refinement_window_reaches_the_tracker_and_a_bad_one_names_the_key(tmp_path):
    """`[flow] refine_window_px` is the tracker's FlowSettings.refine_window_px (0: off); an
    even window is refused at load with the key named."""
    from bubble_rt.estimation.deformation import FlowSettings
    from bubble_rt.estimation.pipeline import capture_settings

    def flow(cfg: DaemonConfig) -> FlowSettings:
        return capture_settings(cfg, realtime=False, layout="sim")["flow"]

    assert flow(DaemonConfig()).refine_window_px == FlowSettings().refine_window_px == 15
    off = DaemonConfig().with_overrides(**{"flow.refine_window_px": 0})
    assert flow(off).refine_window_px == 0
    p = tmp_path / "c.toml"
    p.write_text("[flow]\nrefine_window_px = 14\n")
    with pytest.raises(ConfigError, match=r"flow\.refine_window_px: must be 0 \(none\) or odd"):
        DaemonConfig.load(p)
    with pytest.raises(ValueError, match="refine_window_px must be 0"):
        FlowSettings(refine_window_px=3)
