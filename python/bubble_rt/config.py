"""Daemon configuration: one TOML file mirrored by frozen dataclasses.

Every section is a table in the file; every key has a default, so an empty file is valid.
Every key is declared with :func:`option`: its documentation, and for numbers its range
(:class:`ParamRange`, in the field's metadata) or for words its choices. One validator
(:func:`check_fields`) checks every key when a section is built, whether it comes from a file,
a dict or a command-line flag; loading rejects unknown keys, wrong types and out-of-range
values with a :class:`ConfigError` naming the dotted key, the value and the range (e.g.
``estimator.k_f: must be in [0.0001, 1000] 1/N, got nan``). ``bubble-rt config dump`` prints
the configuration with each key's documentation and range as comments.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from bubble_rt._validate import (
    CONFIG_MAX_BYTES,
    ParamRange,
    PathError,
    read_text_capped,
    regular_file,
    zmq_endpoint_problem,
)
from bubble_rt.estimation.names import DEFAULT_FLOW_METHOD, FLOW_METHODS
from bubble_rt.estimation.params import ESTIMATOR_PARAMS, FLOW_SCALE
from bubble_rt.estimation.registry import estimator_kinds
from bubble_rt.io.codec_names import COLOR_CODECS
from bubble_rt.sensor import PROFILES, SensorProfile, profile_for_layout


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


CAMERA_KINDS = ("sim", "replay", "realsense")
PRESSURE_KINDS = ("camera", "serial", "constant")


def split_source(spec: str) -> tuple[str, str]:
    """``"replay:/data/run.mcap"`` -> ("replay", "/data/run.mcap"); ``"sim"`` -> ("sim", "")."""
    kind, _, arg = spec.partition(":")
    return kind.strip().lower(), arg.strip()


@dataclass(frozen=True)
class CameraConfig:
    """Where RGBD frames come from.

    source: "sim" (built-in demo scene), "sim:<scene name or .toml>", "replay:<recording>"
    (this project's .mcap, a punyo folder or a ROS 2 bag), "realsense" or
    "realsense:<serial number>".
    """

    source: str = option(
        "sim", "sim[:scene], replay:<recording> or realsense[:serial]; opened at start"
    )
    pace: str = option(
        "realtime",
        "replay/sim pacing: realtime (by timestamps / camera rate) or fast (no waiting, every "
        "frame processed, nothing dropped)",
        choices=("realtime", "fast"),
    )
    loop: bool = option(True, "restart a finite source (sim scene, replay) when it ends")
    sim_prerender: bool = option(
        True,
        "simulator: keep the first pass of the scene in memory and replay it (about 2 MB per "
        "640 x 480 frame)",
    )
    width: int = option(640, "RealSense stream width", lo=16, hi=8192, unit="px")
    height: int = option(480, "RealSense stream height", lo=16, hi=8192, unit="px")
    fps: int = option(30, "RealSense frame rate", lo=1, hi=1000, unit="Hz")
    stall_timeout_s: float = option(
        0.5, "no frame for this long: status degraded (camera stalled)", lo=0.01, hi=3600, unit="s"
    )
    replay_settings: str = option(
        "recorded",
        "replay of this project's MCAP: 'recorded' uses the estimator, flow and solver settings "
        "and the fitted mesh stored in the recording (so the replay reproduces the live "
        "forces); 'config' uses this configuration's",
        choices=("recorded", "config"),
    )

    def __post_init__(self) -> None:
        check_fields(self)
        kind, arg = split_source(self.source)
        _check(
            kind in CAMERA_KINDS,
            "source",
            f"unknown camera source {self.source!r}; use sim[:scene], replay:<path> or "
            "realsense[:serial]",
        )
        _check(kind != "replay" or bool(arg), "source", "replay needs a path: replay:<path>")


@dataclass(frozen=True)
class PressureConfig:
    """Where air pressure comes from.

    source: "camera" (the pressure carried by sim/replay frames), "serial:<port>" (a
    microcontroller printing the line protocol, see docs/daemon.md) or "constant:<pascals>".
    """

    source: str = option(
        "camera", "camera, serial:<port> or constant:<pascals> (within [min_pa, max_pa])"
    )
    baud: int = option(115200, "serial port speed", lo=300, hi=10_000_000, unit="baud")
    default_unit: str = option("hPa", "unit of readings that carry none", choices=("hPa", "Pa"))
    #: The default range (absolute) holds every place a sensor works and every squeeze a bubble
    #: survives: 30 kPa is below the lowest ambient (33.7 kPa on Everest's summit), 200 kPa is
    #: the highest ambient (108.5 kPa) plus more than flattening a whole dome raises its air
    #: (a Punyo about 56 kPa, the simulator's bubble about 16 kPa: tests/test_plausibility.py).
    min_pa: float = option(
        30000.0,
        "readings below are rejected as out of range (absolute); a frame's pressure below is "
        "replaced by the last good one (frame degraded), a reference below is refused",
        lo=1,
        hi=1e7,
        unit="Pa",
    )
    max_pa: float = option(
        200000.0,
        "readings above are rejected as out of range (absolute); a frame's pressure above is "
        "replaced by the last good one (frame degraded), a reference above is refused",
        lo=1,
        hi=1e7,
        unit="Pa",
    )
    stale_timeout_s: float = option(
        0.25,
        "pressure older than this at a frame's capture time marks the frame degraded",
        lo=0.001,
        hi=60,
        unit="s",
    )
    buffer: int = option(
        512, "samples kept for interpolation (ring buffer)", lo=2, hi=1_000_000, unit="samples"
    )
    reconnect_s: float = option(
        0.5, "reopen a vanished serial port every this many seconds", lo=0.01, hi=3600, unit="s"
    )

    def __post_init__(self) -> None:
        check_fields(self)
        kind, arg = split_source(self.source)
        _check(
            kind in PRESSURE_KINDS,
            "source",
            f"unknown pressure source {self.source!r}; use camera, serial:<port> or "
            "constant:<pascals>",
        )
        _check(kind != "serial" or bool(arg), "source", "serial needs a port: serial:<port>")
        _check(
            self.min_pa < self.max_pa,
            "max_pa",
            f"must be greater than min_pa ({self.min_pa:g}) and in "
            f"{key_range(_field(self, 'max_pa'))}, got {self.max_pa!r}",
        )
        if kind == "constant":
            try:
                value = float(arg)
            except ValueError:
                raise ConfigError(
                    "source", f"constant pressure {arg!r} is not a number (pascals)"
                ) from None
            rng = ParamRange(self.min_pa, self.max_pa, "Pa (pressure.min_pa, max_pa)")
            err = rng.problem(value)
            _check(err is None, "source", f"constant pressure {err}")


@dataclass(frozen=True)
class NetworkConfig:
    """ZeroMQ endpoints (any ZeroMQ address: tcp://host:port, ipc://path)."""

    pub: str = option("tcp://127.0.0.1:5555", "force frames and status (PUB), bound at start")
    control: str = option("tcp://127.0.0.1:5556", "control requests (ROUTER), bound at start")
    sndhwm: int = option(
        8,
        "messages queued per subscriber before the daemon drops (a slow subscriber never blocks)",
        lo=1,
        hi=100_000,
        unit="messages",
    )
    status_period_s: float = option(1.0, "status message period", lo=0.01, hi=3600, unit="s")

    def __post_init__(self) -> None:
        check_fields(self)
        for n in ("pub", "control"):
            v = getattr(self, n)
            problem = zmq_endpoint_problem(v)
            _check(problem is None, n, str(problem))
        _check(
            self.pub != self.control or self.pub.endswith(":*"),
            "control",
            "must differ from network.pub",
        )


def _estimator_option(key: str) -> Any:
    """The ``[estimator]`` key ``key`` as declared in ``bubble_rt.estimation.params``."""
    p = ESTIMATOR_PARAMS[key]
    r = p.range
    return option(p.file_default, p.doc, lo=r.lo, hi=r.hi, unit=r.unit)


@dataclass(frozen=True)
class EstimatorSection:
    """Force estimator (docs/method.md): a registered kind (``bubble_rt.estimation.registry``):
    "fem" (group-lasso FEM) or "frictionless" (baseline). The parameter keys map onto
    EstimatorConfig through ``bubble_rt.estimation.estimator.CONFIG_KEYS``. Their ranges keep
    the solve regular (outside them it is singular or non-finite, e.g. k_u = 5e-324,
    E = 1e308); ``set_params`` checks the same ranges."""

    #: The parameter keys, their defaults, ranges and docs are declared once, in
    #: bubble_rt.estimation.params (EstimatorConfig's defaults come from there too).
    kind: str = option("fem", "estimator kind", choices=estimator_kinds)
    mesh: str = option(
        "medium",
        "mesh preset (coarse 227, medium 390, fine 749 nodes) or a mesh file, loaded at start",
    )
    fit_mesh: bool = option(True, "fit the mesh onto the membrane seen in the reference frames")
    k_f: float = _estimator_option("k_f")
    k_u: float = _estimator_option("k_u")
    youngs_modulus: float = _estimator_option("youngs_modulus")
    poisson: float = _estimator_option("poisson")
    thickness: float = _estimator_option("thickness")
    k_const: float = _estimator_option("k_const")
    k_linear: float = _estimator_option("k_linear")
    profile: str = option(
        "auto",
        "sensor profile giving the physical constants (bubble_rt.sensor): auto = punyo for "
        "Punyo recordings, ROS 2 bags and RealSense cameras, sim otherwise",
        choices=("auto", *PROFILES),
    )
    ambient_pa: float = _estimator_option("ambient_pa")

    def __post_init__(self) -> None:
        from bubble_rt.mesh import PRESETS

        check_fields(self)
        _check(bool(self.mesh), "mesh", "must name a preset or a mesh file")
        if self.mesh not in PRESETS:
            p = Path(self.mesh)
            _check(
                p.exists(),
                "mesh",
                f"{self.mesh!r} is neither a preset ({', '.join(PRESETS)}) nor an existing file",
            )
            try:
                regular_file("mesh", p)
            except PathError as exc:
                raise ConfigError("mesh", str(exc).removeprefix("mesh: ")) from None

    def sensor_profile(self, layout: str) -> SensorProfile:
        """The profile in use for data of ``layout`` (``auto`` resolves by layout)."""
        return profile_for_layout(layout) if self.profile == "auto" else PROFILES[self.profile]


@dataclass(frozen=True)
class SolverSection:
    """Real-time budget of the ADMM solver (other SolverSettings keep the core's defaults)."""

    time_limit_ms: float = option(
        25.0,
        "per-frame solve budget (0: none) of a warm-started solve; the best iterate so far is "
        "published with solver status time_limit_reached (a cold solve, after a reference or a "
        "tare, runs to certification: its early iterates mark a support of noise)",
        lo=0,
        hi=10_000,
        unit="ms",
    )

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class FlowSection:
    """Optical flow settings passed to the deformation tracker (FlowSettings; its other
    settings keep the deformation module's defaults)."""

    method: str = option(DEFAULT_FLOW_METHOD, "optical flow method", choices=FLOW_METHODS)
    scale: float = option(
        1.0,
        "image scale the flow runs at",
        lo=FLOW_SCALE.lo,
        hi=FLOW_SCALE.hi,
        unit=FLOW_SCALE.unit,
    )
    forward_backward: bool = option(False, "forward-backward consistency check")

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class PlausibilitySection:
    """Plausibility checks: a frame the physics cannot support is published degraded with a
    reason (bubble_rt.estimation.plausibility; docs/daemon.md, Degraded frames)."""

    max_press_speed_m_s: float = option(
        0.5,
        "fastest an object pushes the whole membrane footprint in; it bounds the pressure rate "
        "(rest pressure x footprint x speed / air volume of the sensor profile's bubble: a "
        "Punyo 0.9 kPa per ms at the default); a faster change is replaced by the last good "
        "pressure (frame degraded)",
        lo=0.001,
        hi=100,
        unit="m/s",
    )
    min_valid_fraction: float = option(
        0.5, "fewer nodes tracked than this fraction: frame degraded", lo=0.0, hi=1.0
    )
    dark_level: float = option(
        10.0,
        "colour image mean below this: black (lens covered, lights off), frame degraded",
        lo=0.0,
        hi=255.0,
        unit="of 255",
    )
    bright_level: float = option(
        245.0,
        "colour image mean above this: saturated, frame degraded",
        lo=0.0,
        hi=255.0,
        unit="of 255",
    )
    frozen_frames: int = option(
        5,
        "this many frames in a row bit-identical to their predecessor (colour and depth): "
        "frozen, frame degraded (only for a source whose reference frames differ: a noise-free "
        "simulator repeats itself honestly)",
        lo=1,
        hi=100_000,
        unit="frames",
    )
    max_force_without_contact_n: float = option(
        3.0,
        "a net force above this with no contact node: frame degraded",
        lo=0.0,
        hi=1e4,
        unit="N",
    )
    reference_max_force_n: float = option(
        1.0,
        "the untouched reference frames must read at most this force, else the reference is "
        "refused (wrong camera pose, intrinsics or sensor profile)",
        lo=0.0,
        hi=1e4,
        unit="N",
    )

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class ReferenceSection:
    """The untouched membrane: averaged over the first ``frames`` frames (and on tare)."""

    frames: int = option(
        10,
        "frames averaged into the reference (kept in memory until it is captured: about 2 MB "
        "each at 640 x 480)",
        lo=1,
        hi=300,
        unit="frames",
    )

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class AutoZeroSection:
    """Re-zeroing (docs/daemon.md "Drift and re-zeroing"): while no contact has been seen for
    ``holdoff_s``, the reference (images and pressure) follows the untouched frames, a
    first-order follower of time constant ``time_constant_s`` updated every ``interval_s``.
    ``tare`` is unaffected; the control request ``set_auto_zero`` turns it on or off."""

    enabled: bool = option(True, "follow the drift while untouched")
    time_constant_s: float = option(
        60.0,
        "time constant of the reference following the untouched frames (the drift error "
        "left is about the drift rate times this)",
        lo=0.1,
        hi=86400,
        unit="s",
    )
    interval_s: float = option(
        1.0,
        "time between two re-zero steps while untouched (each re-builds the deformation "
        "tracker, a few ms)",
        lo=0.05,
        hi=3600,
        unit="s",
    )
    holdoff_s: float = option(
        2.0,
        "a frame moves the reference only when no contact and no degraded frame was seen "
        "within this time before and after it",
        lo=0.1,
        hi=3600,
        unit="s",
    )

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class ProcessingConfig:
    """Pipeline: "two_stage" overlaps the deformation of frame k+1 with the solve of frame k."""

    pipeline: str = option("two_stage", "pipeline layout", choices=("two_stage", "single"))
    poll_s: float = option(
        0.05,
        "pause between two stage-one frames waiting for a newer one",
        lo=0.001,
        hi=10,
        unit="s",
    )
    opencv_threads: int = option(
        1,
        "threads of OpenCV's parallel loops in the C++ core (OPENCV_FOR_THREADS_NUM; 0: "
        "OpenCV's default); takes effect only if the core is not loaded yet at start",
        lo=0,
        hi=256,
        unit="threads",
    )

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class RecordingConfig:
    """MCAP recording. ``path`` non-empty: record from start-up."""

    path: str = option(
        "", "record from start-up to this file (created at start; its folder must exist)"
    )
    directory: str = option(".", "where record_start without a path writes (timestamped name)")
    inputs: bool = option(True, "also record the input images and pressure (needed for replay)")
    chunk_size: int = option(
        4 * 1024 * 1024,
        "chunk size: a crash loses at most the unflushed chunk",
        lo=1024,
        hi=1 << 30,
        unit="bytes",
    )
    compression: str = option(
        "zstd",
        "chunk compression (zstd keeps the raw depth lossless at about 0.14 MB a frame; lz4 at "
        "0.24 MB)",
        choices=("zstd", "lz4", "none"),
    )
    color: str = option(
        "jpeg",
        "colour images: jpeg (lossy, about 0.12 MB a frame at quality 90) or png (lossless, "
        "about 0.6 MB); depth is always lossless",
        choices=COLOR_CODECS,
    )
    jpeg_quality: int = option(
        90, "JPEG quality of the colour images (color = jpeg)", lo=1, hi=100, unit="%"
    )
    queue: int = option(
        64,
        "messages waiting for the writer thread; beyond it frames are dropped from the file",
        lo=1,
        hi=100_000,
        unit="messages",
    )
    overwrite: bool = option(False, "replace an existing file at path (otherwise refused)")

    def __post_init__(self) -> None:
        check_fields(self)


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
