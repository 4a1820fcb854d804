"""Sensor profiles (bubble_rt.sensor): the Punyo profile read on a real Punyo press.

The real press is ``../shared/data/punyo-demo-0-press`` (frames 0-4 untouched reference,
15-30 a press up to about 4.8 N with the arm's force/torque reading). The measures are the
held-out check's (``../shared/tools/real-press-report``): the mean magnitude error over the
frames with 1 N or more, and the median |f_est| / |f_true| over the firm hold (4.5 N or more).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.cli import main
from bubble_rt.sensor import PROFILES, PUNYO, SIM, profile, profile_for_layout

PRESS = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0-press"

#: The issue's targets for a real sensor (issue 18): ratio over the firm hold, mean error.
RATIO_RANGE = (0.8, 1.25)
MEAN_ERROR_N = 1.0
#: What calibration on the press itself must reach on those frames (N).
CALIBRATED_ERROR_N = 0.5


def _press_truth() -> np.ndarray:
    rows = json.loads((PRESS / "data.json").read_text())
    w = np.array([r[3][:3] for r in rows])
    return np.linalg.norm(w - w[:5].mean(0), axis=1)


def _read_press(tmp_path: Path, *extra: str) -> tuple[dict[int, float], np.ndarray, dict]:
    out = tmp_path / "press.json"
    args = [str(PRESS), "--reference-frames", "0-4", "--json", str(out), "--no-progress"]
    assert main(["estimate", *args, *extra]) == 0
    res = json.loads(out.read_text())
    est = {f["index"]: float(np.linalg.norm(f["net_force"])) for f in res["frames"]}
    return est, _press_truth(), res


def _scores(est: dict[int, float], truth: np.ndarray) -> tuple[float, float]:
    contact = [i for i in range(15, len(truth)) if truth[i] >= 1.0]
    hold = [i for i in contact if truth[i] >= 4.5]
    assert len(contact) >= 10 and len(hold) >= 3
    err = float(np.mean([abs(est[i] - truth[i]) for i in contact]))
    ratio = float(np.median([est[i] / truth[i] for i in hold]))
    return err, ratio


def test_profiles_are_named_once_and_resolved_by_layout():
    assert set(PROFILES) == {"sim", "punyo"}
    assert profile("punyo") is PUNYO and profile_for_layout("punyo") is PUNYO
    assert profile_for_layout("rosbag") is PUNYO and profile_for_layout("mcap") is SIM
    with pytest.raises(ValueError, match="known: sim, punyo"):
        profile("gelsight")


def test_bubble_constants_are_declared_once_and_read_by_simulator_and_estimator():
    """The simulator's default physics and geometry and the estimator's defaults read the
    profiles' bubbles: nothing restates them."""
    from bubble_rt.estimation.estimator import EstimatorConfig
    from bubble_rt.mesh import MeshGeometry
    from bubble_rt.sim.physics import DEFAULT_REST_DOME_HEIGHT, GasSettings, MembraneMaterial
    from bubble_rt.sim.scene import PhysicsSpec

    b = SIM.bubble
    assert PhysicsSpec() == PhysicsSpec.of(b)
    assert (MembraneMaterial().E, MembraneMaterial().thickness) == (
        b.youngs_modulus_pa,
        b.thickness_m,
    )
    gas = GasSettings()
    assert (gas.gauge_pressure_pa, gas.atmospheric_pa) == (b.gauge_pressure_pa, b.ambient_pa)
    assert DEFAULT_REST_DOME_HEIGHT == b.rest_dome_height_m
    g = MeshGeometry()
    assert (g.semi_axis_x, g.semi_axis_y, g.dome_height) == (
        b.semi_axis_x_m,
        b.semi_axis_y_m,
        b.dome_height_m,
    )
    assert EstimatorConfig().inflation_pa == b.gauge_pressure_pa
    assert EstimatorConfig().ambient_pa == SIM.ambient_pa == b.ambient_pa
    assert (SIM.thickness, SIM.poisson) == (b.thickness_m, b.poisson)
    assert (PUNYO.thickness, PUNYO.poisson) == (PUNYO.bubble.thickness_m, PUNYO.bubble.poisson)


def test_punyo_bubble_reads_the_real_rest_pressure():
    """The identified bubble's ambient plus gauge pressure is what the real sensor reads at
    rest (reference frames 0-4), so a simulated Punyo reads like the real one."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(PRESS)
    p_rest = float(np.mean([rec[i].pressure_pa for i in range(5)]))
    assert abs(PUNYO.bubble.rest_pressure_pa - p_rest) < 50.0


def test_punyo_profile_reads_the_real_press_out_of_the_box(tmp_path):
    """No configuration: the Punyo layout picks the Punyo profile, whose rest tension was
    chosen on simulated Punyo presses (bench/punyo_profile_fit.py), not on this press: an
    out-of-sample check. The force scale and error meet the issue's real-sensor targets, where
    the simulator's constants read about half the force (checked below)."""
    est, truth, res = _read_press(tmp_path)
    assert res["ambient_pa"] == PUNYO.ambient_pa
    err, ratio = _scores(est, truth)
    print(f"punyo profile: mean error {err:.2f} N, hold ratio {ratio:.2f}")
    assert RATIO_RANGE[0] <= ratio <= RATIO_RANGE[1]
    assert err < MEAN_ERROR_N
    # The simulator's constants on the same frames: the factor the profile corrects.
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[estimator]\nprofile = "sim"\n')
    est_sim, _, _ = _read_press(tmp_path, "--config", str(cfg))
    _, ratio_sim = _scores(est_sim, truth)
    assert ratio_sim < 0.6 * ratio


def test_calibration_on_the_real_press_fits_the_rest_tension(tmp_path, capsys):
    """`calibrate --recording` fits the ambient pressure (the rest tension) with E, k_f, k_u
    from the standard atmosphere, and its output brings the error on the press under 0.5 N."""
    out = tmp_path / "punyo.toml"
    argv = ["calibrate", "--recording", str(PRESS), "--out", str(out)]
    assert main([*argv, "--workers", "1", "--no-progress", "--max-evals", "40"]) == 0
    assert "ambient_pa" in capsys.readouterr().out
    est_cfg = tomllib.loads(out.read_text())["estimator"]
    # A rest gauge pressure well above the 5.3 kPa a sea-level ambient gives.
    assert est_cfg["ambient_pa"] < 101325.0 - 5000.0
    est, truth, _ = _read_press(tmp_path, "--config", str(out))
    err, ratio = _scores(est, truth)
    print(f"calibrated: {est_cfg}, mean error {err:.2f} N, hold ratio {ratio:.2f}")
    assert err < CALIBRATED_ERROR_N
    assert RATIO_RANGE[0] <= ratio <= RATIO_RANGE[1]
