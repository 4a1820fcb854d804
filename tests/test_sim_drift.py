"""Slow drift in the simulator: the sealed gas warming or leaking (the physics solves the gas
law with the membrane's volume change), LED warm-up, time compression; computed only when a
scene names them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _sim_fake import FakePhysics, small_scene
from bubble_rt.sim import effects
from bubble_rt.sim.effect_names import EFFECT_DEFAULTS
from bubble_rt.sim.indenters import preset
from bubble_rt.sim.physics import GasSettings, MembraneSim, default_rest_mesh
from bubble_rt.sim.scene import SceneError, parse_scene
from bubble_rt.sim.simulator import Simulator

AWAY = np.diag([1.0, 1.0, 1.0, 1.0])
AWAY[2, 3] = 0.5  # the indenter half a metre above the dome: no contact


@pytest.fixture(scope="module")
def sealed():
    sim = MembraneSim(default_rest_mesh(300), gas=GasSettings(chamber_volume_m3=1.0e-3))
    ref = sim.inflate()
    return sim, ref


def test_warmer_gas_follows_the_gas_law_with_the_bulging_membrane(sealed):
    sim, ref = sealed
    g = sim.gas
    p0 = g.atmospheric_pa + g.gauge_pressure_pa
    warm = (296.15 + 3.0) / 296.15
    sim.set_gas_scale(warm)
    st = sim.solve(preset("round"), AWAY)
    sim.set_gas_scale(1.0)
    assert st.converged
    rigid = p0 * (warm - 1.0)  # about 1 kPa: what a rigid chamber would read
    rise = st.pressure_pa - ref.pressure_pa
    # The dome bulges, so the pressure rises, but by less than in a rigid chamber ...
    assert st.volume_m3 > ref.volume_m3
    assert 0.2 * rigid < rise < 0.95 * rigid
    # ... and exactly as the gas law says for the new volume.
    pv0 = p0 * (ref.volume_m3 + g.chamber_volume_m3)
    pv = st.pressure_pa * (st.volume_m3 + g.chamber_volume_m3)
    assert pv == pytest.approx(pv0 * warm, rel=1e-6)
    assert np.abs(st.contact_forces).max() == 0.0


def test_a_leak_lowers_the_pressure_and_the_dome(sealed):
    sim, ref = sealed
    sim.set_gas_scale(0.99)
    st = sim.solve(preset("round"), AWAY)
    sim.set_gas_scale(1.0)
    assert st.pressure_pa < ref.pressure_pa and st.volume_m3 < ref.volume_m3


def test_gas_scale_is_temperature_ratio_times_gas_left():
    temp = dict(EFFECT_DEFAULTS["gas_temperature_drift"], kelvin=4.0, ramp_s=100.0, start_s=50.0)
    leak = {"fraction_per_hour": 0.01}
    t0 = temp["temperature_k"]
    assert effects.gas_temperature_k(temp, 0.0) == t0
    assert effects.gas_temperature_k(temp, 100.0) == pytest.approx(t0 + 2.0)
    assert effects.gas_temperature_k(temp, 1e6) == pytest.approx(t0 + 4.0)
    assert effects.gas_amount(leak, 7200.0) == pytest.approx(0.99**2)
    s = effects.gas_scale(temp, leak, 7200.0)
    assert s == pytest.approx((t0 + 4.0) / t0 * 0.99**2)
    assert effects.gas_scale(None, None, 7200.0) == 1.0


def test_illumination_drift_dims_and_offsets_as_the_leds_settle():
    p = {"gain_loss": 0.1, "offset": 4.0, "settle_s": 100.0}
    rgb = np.full((4, 5, 3), 200, np.uint8)
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(effects.illumination_drift(rgb, p, rng, 0.0), rgb)
    r = 1.0 - np.exp(-1.0)
    out = effects.illumination_drift(rgb, p, rng, 100.0)
    assert int(out[0, 0, 0]) == round(200 * (1 - 0.1 * r) + 4.0 * r)
    late = effects.illumination_drift(rgb, p, rng, 1e5)
    assert int(late[0, 0, 0]) == round(200 * 0.9 + 4.0)


def test_illumination_drift_reads_drift_time():
    eff = (("illumination_drift", tuple(EFFECT_DEFAULTS["illumination_drift"].items())),)
    rgb = np.full((4, 5, 3), 200, np.uint8)
    slow, _ = effects.apply_image_effects(eff, 0, 1, 60.0, rgb, None, time_scale=1.0)
    fast, _ = effects.apply_image_effects(eff, 0, 1, 60.0, rgb, None, time_scale=60.0)
    assert int(slow[0, 0, 0]) > int(fast[0, 0, 0])  # an hour in, the LEDs dimmed more


def test_gas_drift_needs_a_sealed_gas():
    with pytest.raises(SceneError, match="gas_compression"):
        small_scene("['gas_temperature_drift']")
    with pytest.raises(SceneError, match="gas_compression"):
        small_scene("['gas_leak']")
    small_scene("['gas_compression', 'gas_leak']")


def test_time_scale_is_parsed_and_keys_the_physics_only_with_gas_drift():
    base = small_scene("['gas_compression']")
    text = "[rates]\ntime_scale = 60.0\n"
    assert base.rates.time_scale == 1.0
    scaled = base.with_changes(rates=parse_scene_rates(text))
    assert scaled.rates.time_scale == 60.0
    assert scaled.physics_key("v") == base.physics_key("v")
    drifting = small_scene("['gas_compression', 'gas_temperature_drift']")
    assert drifting.physics_key("v") != base.physics_key("v")
    assert drifting.with_changes(rates=scaled.rates).physics_key("v") != drifting.physics_key("v")
    with pytest.raises(SceneError, match="time_scale"):
        parse_scene_rates("[rates]\ntime_scale = 0.0\n")


def parse_scene_rates(rates_toml: str):  # type: ignore[no-untyped-def]
    text = (
        'name = "r"\n'
        "[trajectory]\nkeyframes = [{ t = 0.0, at = [0.0, 0.0], depth = -0.002 }]\n" + rates_toml
    )
    return parse_scene(text).rates


def test_drift_scene_names_the_drift_effects():
    from bubble_rt.sim.scene import load_scene

    sc = load_scene("drift")
    for name in ("gas_temperature_drift", "gas_leak", "illumination_drift", "gas_compression"):
        assert sc.has(name)
    hour = sc.frames / sc.rates.camera_hz * sc.rates.time_scale
    assert hour >= 3600.0
    assert 2.0 <= sc.params("gas_temperature_drift")["kelvin"] <= 5.0


class GasRecordingPhysics(FakePhysics):
    """The kinematic fake, recording the gas scale the simulator sets before each solve."""

    def __init__(self) -> None:
        super().__init__()
        self.scales: list[float] = []

    def create(self, scene, rest_mesh):  # type: ignore[no-untyped-def]
        sim = super().create(scene, rest_mesh)
        sim.set_gas_scale = self.scales.append
        return sim


def test_gas_drift_reaches_the_physics_only_when_named():
    plain = GasRecordingPhysics()
    sim = Simulator(small_scene("['gas_compression']", frames=4), physics=plain, use_cache=False)
    list(sim.frames())
    assert plain.scales == [] and not sim.stages_run & {"gas_temperature_drift", "gas_leak"}

    drifting = GasRecordingPhysics()
    sc = small_scene("['gas_compression', 'gas_temperature_drift', 'gas_leak']", frames=4)
    sc = sc.with_changes(rates=replace(sc.rates, time_scale=3600.0 * 30.0))  # 1 frame: 1 h
    sim = Simulator(sc, physics=drifting, use_cache=False)
    list(sim.frames())
    temp, leak = sc.params("gas_temperature_drift"), sc.params("gas_leak")
    expect = [effects.gas_scale(temp, leak, k * 3600.0) for k in range(4)]
    assert drifting.scales == pytest.approx(expect)
    assert expect[0] == 1.0 and expect[1] > 1.0  # warming outweighs the leak
    assert {"gas_temperature_drift", "gas_leak"} <= sim.stages_run
