"""bubble_rt.estimation.params: each estimator parameter declared once, and every other place
that names one (EstimatorConfig, the [estimator] keys, set_params, the registry, the wire)
reads the same key, default and range."""

from __future__ import annotations

import dataclasses

import pytest
from bubble_rt.config import ESTIMATOR_RANGES, ConfigError, DaemonConfig, FlowSection, key_range
from bubble_rt.estimation.deformation import FlowSettings
from bubble_rt.estimation.estimator import CONFIG_KEYS, EstimatorConfig
from bubble_rt.estimation.params import ESTIMATOR_PARAMS, FLOW_SCALE, LIVE_PARAMS
from bubble_rt.estimation.registry import estimator_kind, estimator_kinds
from bubble_rt.io.protocol import PARAM_NAMES


def test_the_wire_carries_exactly_the_live_parameters():
    assert PARAM_NAMES == LIVE_PARAMS


def test_every_kind_changes_only_declared_live_parameters():
    assert estimator_kind("fem").params == LIVE_PARAMS
    for name in estimator_kinds():
        assert set(estimator_kind(name).params) <= set(LIVE_PARAMS), name


def test_estimator_config_defaults_and_keys_are_the_declared_ones():
    est = EstimatorConfig()
    assert set(CONFIG_KEYS) == set(ESTIMATOR_PARAMS)
    for key, p in ESTIMATOR_PARAMS.items():
        value = getattr(est, p.field)
        if p.material is not None:
            value = getattr(value, p.material)
        assert value == p.default, key


def test_config_keys_have_the_declared_defaults_ranges_and_docs():
    section = DaemonConfig().estimator
    by_name = {f.name: f for f in dataclasses.fields(section)}
    for key, p in ESTIMATOR_PARAMS.items():
        assert getattr(section, key) == p.file_default, key
        assert key_range(by_name[key]) == p.range, key
        assert by_name[key].metadata["doc"] == p.doc, key
        assert ESTIMATOR_RANGES[key] == p.range, key


@pytest.mark.parametrize("key", sorted(ESTIMATOR_PARAMS))
def test_a_value_just_outside_the_declared_range_is_refused_by_the_loader(key):
    r = ESTIMATOR_PARAMS[key].range
    with pytest.raises(ConfigError) as info:
        DaemonConfig.from_dict({"estimator": {key: r.hi * 1.5 + 1.0}})
    assert info.value.key == f"estimator.{key}"


def test_flow_scale_has_one_range_in_the_config_and_the_tracker():
    below = FLOW_SCALE.lo / 2
    with pytest.raises(ValueError, match="flow scale"):
        FlowSettings(scale=below)
    with pytest.raises(ConfigError):
        FlowSection(scale=below)
    FlowSettings(scale=FLOW_SCALE.lo)
    FlowSection(scale=FLOW_SCALE.lo)
