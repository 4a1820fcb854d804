"""The configuration page of the docs site against the code's declarations.

The page (docs/configuration.md) is generated at build time by docs/hooks/config_page.py; these
tests render it the same way and compare it with what ``bubble-rt config dump`` prints and with
what the loader accepts, so a key missing from the page, a wrong default or a range the loader
does not enforce fails here (``mkdocs build --strict`` in CI checks links and docstrings).
"""

from __future__ import annotations

import importlib.util
import re
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import tomli_w
from bubble_rt import config

ROOT = Path(__file__).resolve().parents[1]
ROW = re.compile(r"^\| `([^`]+)` \| `([^`]*)` \| (.*?) \| (.*) \|$")
RANGE = re.compile(r"^\[([^,\]]+), ([^\]]+)\]")


def _hook() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "config_page", ROOT / "docs" / "hooks" / "config_page.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _page_rows() -> dict[str, tuple[str, str]]:
    """Dotted key -> (default as written, accepted values as written) from the rendered page."""
    hook = _hook()
    page = hook.render((ROOT / "docs" / "configuration.md").read_text())
    rows: dict[str, tuple[str, str]] = {}
    for line in page.splitlines():
        m = ROW.match(line)
        if m:
            assert m.group(1) not in rows, f"{m.group(1)} listed twice"
            rows[m.group(1)] = (m.group(2), m.group(3))
    return rows


def _flatten(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flatten(v, prefix + k + "."))
        else:
            out[prefix + k] = v
    return out


def _nested(dotted: str, value: Any) -> dict[str, Any]:
    *parents, last = dotted.split(".")
    data: dict[str, Any] = {last: value}
    for p in reversed(parents):
        data = {p: data}
    return data


def test_page_lists_every_key_config_dump_prints_with_its_default() -> None:
    dumped = _flatten(tomllib.loads(config.dump_toml(config.default_config())))
    rows = _page_rows()
    assert dumped, "config dump printed no key"
    assert sorted(rows) == sorted(dumped), "page and `config dump` list different keys"
    for key, value in dumped.items():
        written = tomli_w.dumps({"k": value}).split("=", 1)[1].strip()
        assert rows[key][0] == written, f"{key}: page default {rows[key][0]}, dump {written}"


def test_page_ranges_are_what_the_loader_enforces() -> None:
    """Just outside each range written on the page, loading fails naming that key."""
    checked = 0
    for key, (default, accepted) in _page_rows().items():
        m = RANGE.match(accepted)
        if m is None:
            continue
        lo, hi = float(m.group(1)), float(m.group(2))
        if isinstance(tomllib.loads(f"k = {default}")["k"], int):
            outside: list[Any] = [int(lo) - 1, int(hi) + 1]
        else:
            outside = [lo - max(abs(lo) * 1e-3, 1e-12), hi + abs(hi) * 1e-3]
        for value in outside:
            with pytest.raises(config.ConfigError) as exc:
                config.DaemonConfig.from_dict(_nested(key, value))
            assert exc.value.key == key, f"{key} = {value!r} refused under {exc.value.key!r}"
        checked += 1
    assert checked >= 20, f"only {checked} ranged keys found on the page"


def test_page_choices_are_the_declared_ones() -> None:
    rows = _page_rows()
    declared = {k: config.key_choices(f) for k, f in config.keys()}
    for key, choices in declared.items():
        if choices is None:
            continue
        written = re.findall(r"`([^`]+)`", rows[key][1])
        assert tuple(written) == tuple(choices), f"{key}: page {written}, code {choices}"
        with pytest.raises(config.ConfigError) as exc:
            config.DaemonConfig.from_dict(_nested(key, "not-a-choice"))
        assert exc.value.key == key


def test_site_builds_the_generated_page() -> None:
    """The page keeps its marker and the site's configuration registers the hook and the page."""
    hook = _hook()
    assert (ROOT / "docs" / "configuration.md").read_text().count(hook.MARKER) == 1
    site = (ROOT / "mkdocs.yml").read_text()
    assert "docs/hooks/config_page.py" in site
    assert re.search(r"^\s+- Configuration: configuration\.md$", site, re.MULTILINE)


def test_simulator_effects_table_states_the_defaults():
    # docs/simulator.md's table of effects is written by hand: every effect with every
    # parameter at its EFFECT_DEFAULTS value (it had kept the pre-D405 defaults for a while).
    from bubble_rt.sim.effect_names import EFFECT_DEFAULTS

    text = (ROOT / "docs" / "simulator.md").read_text()
    rows = {m[1]: m[2] for m in re.finditer(r"^\| `([a-z_]+)` \| ([^|]*) \|", text, re.M)}
    for effect, params in EFFECT_DEFAULTS.items():
        assert effect in rows, f"{effect} missing from docs/simulator.md"
        written = {
            k: float(v) for k, v in re.findall(r"`([a-z_0-9]+)` \(([-0-9.e+]+)\)", rows[effect])
        }
        assert written == pytest.approx(params), effect
