"""Daemon configuration: one TOML file mirrored by frozen dataclasses.

Every section is a table in the file; every key has a default, so an empty file is valid.
Every key is declared with :func:`option`: its documentation, and for numbers its range
(:class:`ParamRange`, in the field's metadata) or for words its choices. One validator
(:func:`check_fields`) checks every key when a section is built, whether it comes from a file,
a dict or a command-line flag; loading rejects unknown keys, wrong types and out-of-range
values with a :class:`ConfigError` naming the dotted key, the value and the range (e.g.
``estimator.k_f: must be in [0.0001, 1000] 1/N, got nan``). ``bubble-rt config dump`` prints
the configuration with each key's documentation and range as comments.

The package reads in three parts: :mod:`bubble_rt.config.options` (how a key is declared and
checked, and the builder from TOML tables), :mod:`bubble_rt.config.tables` (one dataclass per
section) and this module (:class:`DaemonConfig`, loading, the key listing and ``config dump``).
Every public name is importable from ``bubble_rt.config``.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from bubble_rt._validate import CONFIG_MAX_BYTES, ParamRange, PathError, read_text_capped
from bubble_rt.config.options import (
    Choices,
    ConfigError,
    _build,
    _check,
    check_fields,
    key_choices,
    key_comment,
    key_range,
    option,
)
from bubble_rt.config.tables import (
    CAMERA_KINDS,
    PRESSURE_KINDS,
    AutoZeroSection,
    CameraConfig,
    EstimatorSection,
    FlowSection,
    NetworkConfig,
    PlausibilitySection,
    PressureConfig,
    ProcessingConfig,
    RecordingConfig,
    ReferenceSection,
    SolverSection,
    split_source,
)

#: The public names (``from bubble_rt.config import X``; the API page documents these): the
#: declaration machinery, the sections in file order, the whole configuration and its listing.
__all__ = [
    "ConfigError",
    "Choices",
    "option",
    "key_range",
    "key_choices",
    "check_fields",
    "CAMERA_KINDS",
    "PRESSURE_KINDS",
    "split_source",
    "CameraConfig",
    "PressureConfig",
    "NetworkConfig",
    "EstimatorSection",
    "SolverSection",
    "FlowSection",
    "PlausibilitySection",
    "ReferenceSection",
    "AutoZeroSection",
    "ProcessingConfig",
    "RecordingConfig",
    "DaemonConfig",
    "ESTIMATOR_RANGES",
    "param_problem",
    "sections",
    "keys",
    "key_comment",
    "dump_toml",
    "default_config",
]


@dataclass(frozen=True)
class DaemonConfig:
    """The whole daemon configuration (one TOML file, one table per section)."""

    sensor_id: str = option("bubble0", "letters, digits, '-' or '_' (it becomes a topic)")
    camera: CameraConfig = field(default_factory=CameraConfig)
    pressure: PressureConfig = field(default_factory=PressureConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    estimator: EstimatorSection = field(default_factory=EstimatorSection)
    solver: SolverSection = field(default_factory=SolverSection)
    flow: FlowSection = field(default_factory=FlowSection)
    plausibility: PlausibilitySection = field(default_factory=PlausibilitySection)
    reference: ReferenceSection = field(default_factory=ReferenceSection)
    processing: ProcessingConfig = field(default_factory=ProcessingConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    auto_zero: AutoZeroSection = field(default_factory=AutoZeroSection)
    shutdown_timeout_s: float = option(
        2.0,
        "the daemon stops within this time after SIGINT/SIGTERM (threads joined, file finalised)",
        lo=0.1,
        hi=600,
        unit="s",
    )

    def __post_init__(self) -> None:
        check_fields(self)
        _check(
            bool(self.sensor_id) and all(c.isalnum() or c in "-_" for c in self.sensor_id),
            "sensor_id",
            f"must be letters, digits, '-' or '_' (it becomes a topic), got {self.sensor_id!r}",
        )

    # ---------------------------------------------------------------- conversion
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_toml(self) -> str:
        import tomli_w

        return tomli_w.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DaemonConfig:
        return _build(cls, data, "")

    @classmethod
    def load(cls, path: str | Path, option: str = "config file") -> DaemonConfig:
        """Read and validate a TOML file: a regular file (symlinks followed) of at most
        ``CONFIG_MAX_BYTES``; ``option`` names where the path came from in errors."""
        p = Path(path)
        try:
            text = read_text_capped(option, p, CONFIG_MAX_BYTES)
        except PathError as exc:
            raise ConfigError("", str(exc)) from exc
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"{p} is not valid TOML: {exc}") from exc
        return cls.from_dict(data)

    def with_overrides(self, **dotted: Any) -> DaemonConfig:
        """A copy with dotted keys replaced, e.g. ``with_overrides(**{"camera.source": "sim"})``."""
        data = self.to_dict()
        for key, value in dotted.items():
            if value is None:
                continue
            node = data
            parts = key.split(".")
            for part in parts[:-1]:
                node = node[part]
            node[parts[-1]] = value
        return DaemonConfig.from_dict(data)


#: Ranges of the estimator parameters (from the [estimator] keys), the one place both
#: configuration loading and the live ``set_params`` control request check them.
ESTIMATOR_RANGES: dict[str, ParamRange] = {
    f.name: r for f in fields(EstimatorSection) if (r := key_range(f)) is not None
}


def param_problem(name: str, value: Any) -> str | None:
    """None if ``value`` is acceptable for estimator parameter ``name``, else the reason."""
    rng = ESTIMATOR_RANGES.get(name)
    if rng is None:
        return f"unknown parameter; expected one of {', '.join(ESTIMATOR_RANGES)}"
    return rng.problem(value)


def sections() -> dict[str, type]:
    """Section name -> its dataclass ("" for the top-level keys of DaemonConfig)."""
    out: dict[str, type] = {"": DaemonConfig}
    for f in fields(DaemonConfig):
        if dataclasses.is_dataclass(f.default_factory):  # type: ignore[arg-type]
            out[f.name] = f.default_factory  # type: ignore[assignment]
    return out


def keys() -> list[tuple[str, dataclasses.Field[Any]]]:
    """Every configuration key: (dotted name, its dataclass field), sections expanded."""
    out = []
    for sec, cls in sections().items():
        for f in fields(cls):
            if sec == "" and f.name in sections():
                continue
            out.append((f"{sec}.{f.name}" if sec else f.name, f))
    return out


def dump_toml(cfg: DaemonConfig) -> str:
    """The configuration as TOML with every key's documentation and range as comments."""
    import textwrap

    import tomli_w

    def lines(obj: Any) -> list[str]:
        out = []
        for f in fields(obj):
            if dataclasses.is_dataclass(getattr(obj, f.name)):
                continue
            for c in textwrap.wrap(key_comment(f), 96):
                out.append(f"# {c}")
            out.append(tomli_w.dumps({f.name: getattr(obj, f.name)}).rstrip("\n"))
        return out

    text = ["# bubble_rt daemon configuration (bubble-rt config dump)", *lines(cfg)]
    for name, cls in sections().items():
        if not name:
            continue
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        text += ["", f"# {doc}", f"[{name}]", *lines(getattr(cfg, name))]
    return "\n".join(text) + "\n"


def default_config() -> DaemonConfig:
    return DaemonConfig()
