"""How a configuration key is declared and checked: :func:`option` (default, documentation,
range or choices in the field's metadata), :func:`check_fields` (the one validator every section
runs when built), and the builder that turns a TOML table into a section dataclass, naming the
dotted key of any error (:class:`ConfigError`).

The sections themselves are in :mod:`bubble_rt.config.tables`; import everything from
:mod:`bubble_rt.config`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import field, fields, replace
from typing import Any

from bubble_rt._validate import ParamRange


class ConfigError(ValueError):
    """Invalid configuration; ``key`` is the dotted name of the offending key."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key
        self.message = message


def _check(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(key, message)


Choices = tuple[str, ...] | Callable[[], tuple[str, ...]]


def option(
    default: Any,
    doc: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    unit: str = "",
    choices: Choices | None = None,
) -> Any:
    """A configuration key: its default, documentation and accepted values (checked by
    :func:`check_fields`; numbers need ``lo``/``hi``)."""
    meta: dict[str, Any] = {"doc": doc}
    if isinstance(default, (int, float)) and not isinstance(default, bool):
        if lo is None or hi is None:
            raise TypeError(f"numeric option {default!r} needs a range (lo, hi)")
        meta["range"] = ParamRange(float(lo), float(hi), unit, integer=isinstance(default, int))
    if choices is not None:
        meta["choices"] = choices
    return field(default=default, metadata=meta)


def key_range(f: dataclasses.Field[Any]) -> ParamRange | None:
    """The range of a numeric key (None for other keys)."""
    return f.metadata.get("range")


def key_choices(f: dataclasses.Field[Any]) -> tuple[str, ...] | None:
    """The accepted words of a key with a fixed set (None for other keys)."""
    c = f.metadata.get("choices")
    return c() if callable(c) else c


def _field(obj: Any, name: str) -> dataclasses.Field[Any]:
    return next(f for f in fields(obj) if f.name == name)


def check_fields(obj: Any) -> None:
    """Check every key of section ``obj`` against its declared range or choices."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        rng = key_range(f)
        if rng is not None:
            err = rng.problem(v)
            _check(err is None, f.name, err or "")
        choices = key_choices(f)
        if choices is not None:
            _check(
                v in choices,
                f.name,
                "must be " + _one_of(choices) + f", got {v!r}",
            )
        if isinstance(f.default, bool):
            _check(isinstance(v, bool), f.name, f"must be true or false, got {v!r}")
        elif isinstance(f.default, str):
            _check(isinstance(v, str), f.name, f"must be a string, got {v!r}")


def _one_of(choices: tuple[str, ...]) -> str:
    words = [repr(c) for c in choices]
    return words[0] if len(words) == 1 else "one of " + ", ".join(words)


def _type_ok(value: Any, default: Any) -> bool:
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if isinstance(default, str):
        return isinstance(value, str)
    return True


def _build(cls: Any, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(prefix.rstrip("."), f"must be a table, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}
    for key in data:
        if key not in known:
            raise ConfigError(
                prefix + key, f"unknown key; expected one of {', '.join(sorted(known))}"
            )
    defaults = cls()
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        default = getattr(defaults, name)
        if dataclasses.is_dataclass(default):
            kwargs[name] = _build(type(default), value, prefix + name + ".")
            continue
        rng = key_range(known[name])
        if not _type_ok(value, default):
            hint = f"; range {rng.text()}" if rng is not None else ""
            raise ConfigError(
                prefix + name,
                f"expected {type(default).__name__}, got {type(value).__name__} ({value!r}){hint}",
            )
        if rng is not None:  # before float(): a huge int must be refused, not overflow
            err = rng.problem(value)
            _check(err is None, prefix + name, err or "")
        kwargs[name] = float(value) if isinstance(default, float) else value
    try:
        return replace(defaults, **kwargs)
    except ConfigError as exc:
        raise ConfigError(prefix + exc.key, exc.message) from None


def key_comment(f: dataclasses.Field[Any]) -> str:
    """``config dump``'s comment for a key: its documentation and accepted values."""
    doc = f.metadata.get("doc", "")
    rng, choices = key_range(f), key_choices(f)
    if rng is not None:
        doc += f"; range {rng.text()}"
    elif choices is not None:
        doc += "; " + _one_of(choices)
    elif isinstance(f.default, bool):
        doc += "; true or false"
    return doc
