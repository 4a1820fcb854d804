"""MkDocs hook: the configuration page, generated from bubble_rt.config's declarations.

``docs/configuration.md`` holds the prose and one marker line (:data:`MARKER`); the hook
replaces the marker with one table per section, built from the same declarations the loader
checks (:func:`bubble_rt.config.keys`, ``key_range``, ``key_choices``, the ``doc`` of each
``option`` and the defaults of :func:`bubble_rt.config.default_config`). A key added to a
section dataclass appears on the page at the next build; ``tests/test_docs.py`` checks that the
page names every key ``bubble-rt config dump`` prints, with the same default.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path
from typing import Any

#: The line of docs/configuration.md that the generated tables replace.
MARKER = "<!-- generated: configuration keys -->"

_PYTHON = Path(__file__).resolve().parents[2] / "python"


def _escape(text: str) -> str:
    """Markdown-safe text for a table cell: code spans (RST ``x`` or Markdown `x`) kept as
    code, elsewhere pipes, HTML brackets and emphasis characters escaped."""
    out = []
    for i, part in enumerate(re.split(r"``(.+?)``|`([^`]+)`", text)):
        if part is None:
            continue
        if i % 3:  # a code span's content
            out.append("`" + part.replace("|", "\\|") + "`")
            continue
        for a, b in (("\\", "\\\\"), ("|", "\\|"), ("<", "&lt;"), ("*", "\\*"), ("_", "\\_")):
            part = part.replace(a, b)
        out.append(part)
    return "".join(out)


def _toml_value(value: Any) -> str:
    """``value`` as TOML writes it (what ``bubble-rt config dump`` prints)."""
    import tomli_w

    return tomli_w.dumps({"k": value}).split("=", 1)[1].strip()


def _default(cfg: Any, dotted: str) -> Any:
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    return node


def _accepted(config: Any, f: dataclasses.Field[Any]) -> str:
    rng, choices = config.key_range(f), config.key_choices(f)
    if rng is not None:
        return _escape(rng.text())
    if choices is not None:
        return ", ".join(f"`{c}`" for c in choices)
    if isinstance(f.default, bool):
        return "`true`, `false`"
    return "text (see meaning)" if isinstance(f.default, str) else "see meaning"


def config_tables() -> str:
    """Markdown: one table per configuration section, every key with default, range, doc."""
    import bubble_rt.config as config

    cfg = config.default_config()
    by_section: dict[str, list[tuple[str, dataclasses.Field[Any]]]] = {}
    for dotted, f in config.keys():
        section = dotted.rpartition(".")[0]
        by_section.setdefault(section, []).append((dotted, f))
    out: list[str] = []
    for section, cls in config.sections().items():
        rows = by_section.pop(section, [])
        if not rows:
            continue
        title = f"`[{section}]`" if section else "Top level"
        doc = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())
        out += [f"### {title}", "", _escape(doc) if section else "Keys outside any table.", ""]
        out += ["| key | default | accepted | meaning |", "|---|---|---|---|"]
        for dotted, f in rows:
            default = _toml_value(_default(cfg, dotted))
            meaning = _escape(str(f.metadata.get("doc", "")))
            out.append(f"| `{dotted}` | `{default}` | {_accepted(config, f)} | {meaning} |")
        out.append("")
    if by_section:  # a key outside the listed sections would be silently lost otherwise
        raise RuntimeError(f"configuration keys in no section: {sorted(by_section)}")
    return "\n".join(out)


def render(markdown: str) -> str:
    """``markdown`` (the source of docs/configuration.md) with the marker replaced."""
    if markdown.count(MARKER) != 1:
        raise RuntimeError(f"docs/configuration.md must contain {MARKER!r} exactly once")
    return markdown.replace(MARKER, config_tables())


def on_config(config: Any) -> Any:
    """Document the source tree being built (before any installed copy of the package)."""
    if str(_PYTHON) not in sys.path:
        sys.path.insert(0, str(_PYTHON))
    return config


def on_page_markdown(markdown: str, page: Any, **_: Any) -> str:
    if page.file.src_uri == "configuration.md":
        return render(markdown)
    return markdown
