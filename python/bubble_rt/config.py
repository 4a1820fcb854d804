"""Daemon configuration: one TOML file mirrored by frozen dataclasses.

Every section is a table in the file; every key has a default, so an empty file is valid.
Loading rejects unknown keys, wrong types and out-of-range values with a :class:`ConfigError`
whose message starts with the dotted key at fault (e.g. ``estimator.k_f: must be > 0``).
``bubble-rt config dump`` prints the defaults.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from bubble_rt.estimation.names import DEFAULT_FLOW_METHOD, FLOW_METHODS
from bubble_rt.estimation.registry import estimator_kinds


class ConfigError(ValueError):
    """Invalid configuration; ``key`` is the dotted name of the offending key."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key
        self.message = message


def _check(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(key, message)


def _positive(obj: Any, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _check(math.isfinite(v) and v > 0, n, f"must be a positive number, got {v!r}")


def _non_negative(obj: Any, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _check(math.isfinite(v) and v >= 0, n, f"must be >= 0, got {v!r}")


@dataclass(frozen=True)
class ParamRange:
    """Accepted values of one numeric parameter: finite and within [lo, hi] (units for messages)."""

    lo: float
    hi: float
    unit: str = ""

    def problem(self, value: Any) -> str | None:
        """None when ``value`` is acceptable, else what is wrong with it (no key name)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"must be a number, got {value!r}"
        v = float(value)
        if not math.isfinite(v):
            return f"must be finite, got {v!r}"
        if not self.lo <= v <= self.hi:
            unit = f" {self.unit}" if self.unit else ""
            return f"must be in [{self.lo:g}, {self.hi:g}]{unit}, got {v!r}"
        return None


#: Ranges of the estimator parameters, the one place both configuration loading
#: (``[estimator]``) and the live ``set_params`` control request check them. Values outside
#: these ranges make the solve singular or non-finite (e.g. k_u = 5e-324, E = 1e308).
ESTIMATOR_RANGES: dict[str, ParamRange] = {
    "k_f": ParamRange(1e-4, 1e3, "1/N"),
    "k_u": ParamRange(1e2, 1e10, "1/m^2"),
    "youngs_modulus": ParamRange(1e4, 1e8, "Pa"),
    "poisson": ParamRange(0.0, 0.5),
    "thickness": ParamRange(1e-5, 1e-2, "m"),
    "k_const": ParamRange(0.0, 1e6, "Pa"),
    "k_linear": ParamRange(0.0, 1e3),
}


def param_problem(name: str, value: Any) -> str | None:
    """None if ``value`` is acceptable for estimator parameter ``name``, else the reason."""
    rng = ESTIMATOR_RANGES.get(name)
    if rng is None:
        return f"unknown parameter; expected one of {', '.join(ESTIMATOR_RANGES)}"
    return rng.problem(value)


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
    (this project's .mcap or a punyo folder), "realsense" or "realsense:<serial number>".
    """

    source: str = "sim"
    #: Replay/sim pacing: "realtime" (by timestamps / camera rate) or "fast" (no waiting,
    #: every frame processed, nothing dropped).
    pace: str = "realtime"
    #: Restart a finite source (sim scene, replay) from the beginning when it ends.
    loop: bool = True
    #: Simulator: keep the first pass of the scene in memory and replay it (saves the
    #: rendering CPU for the estimator; about 2 MB per 640 x 480 frame).
    sim_prerender: bool = True
    #: RealSense stream settings (the simulator uses its scene's camera and rate).
    width: int = 640
    height: int = 480
    fps: int = 30
    #: No frame for this long: status degraded ("camera stalled").
    stall_timeout_s: float = 0.5

    def __post_init__(self) -> None:
        kind, arg = split_source(self.source)
        _check(
            kind in CAMERA_KINDS,
            "source",
            f"unknown camera source {self.source!r}; use sim[:scene], replay:<path> or "
            "realsense[:serial]",
        )
        _check(kind != "replay" or bool(arg), "source", "replay needs a path: replay:<path>")
        _check(self.pace in ("realtime", "fast"), "pace", "must be 'realtime' or 'fast'")
        _positive(self, "width", "height", "fps", "stall_timeout_s")


@dataclass(frozen=True)
class PressureConfig:
    """Where air pressure comes from.

    source: "camera" (the pressure carried by sim/replay frames), "serial:<port>" (a
    microcontroller printing the line protocol, see README) or "constant:<pascals>".
    """

    source: str = "camera"
    baud: int = 115200
    #: Unit of readings that carry none: "hPa" or "Pa".
    default_unit: str = "hPa"
    #: Readings outside [min_pa, max_pa] are rejected as out of range (absolute pressure).
    min_pa: float = 30000.0
    max_pa: float = 200000.0
    #: Pressure older than this at a camera frame's capture time marks the frame degraded.
    stale_timeout_s: float = 0.25
    #: Samples kept for interpolation (a ring buffer; about 5 s at 100 Hz).
    buffer: int = 512
    #: Reopen a vanished serial port every this many seconds.
    reconnect_s: float = 0.5

    def __post_init__(self) -> None:
        kind, arg = split_source(self.source)
        _check(
            kind in PRESSURE_KINDS,
            "source",
            f"unknown pressure source {self.source!r}; use camera, serial:<port> or "
            "constant:<pascals>",
        )
        _check(kind != "serial" or bool(arg), "source", "serial needs a port: serial:<port>")
        if kind == "constant":
            try:
                float(arg)
            except ValueError:
                raise ConfigError("source", f"constant pressure {arg!r} is not a number") from None
        _check(self.default_unit in ("hPa", "Pa"), "default_unit", "must be 'hPa' or 'Pa'")
        _positive(self, "baud", "min_pa", "max_pa", "stale_timeout_s", "buffer", "reconnect_s")
        _check(self.min_pa < self.max_pa, "max_pa", "must be greater than min_pa")


@dataclass(frozen=True)
class NetworkConfig:
    """ZeroMQ endpoints (any ZeroMQ address: tcp://host:port, ipc://path)."""

    pub: str = "tcp://127.0.0.1:5555"
    control: str = "tcp://127.0.0.1:5556"
    #: Messages queued per subscriber before the daemon drops (a slow subscriber never blocks).
    sndhwm: int = 8
    #: Status message period, seconds.
    status_period_s: float = 1.0

    def __post_init__(self) -> None:
        for n in ("pub", "control"):
            v = getattr(self, n)
            _check("://" in v, n, f"not a ZeroMQ address: {v!r} (e.g. tcp://127.0.0.1:5555)")
        _check(
            self.pub != self.control or self.pub.endswith(":*"),
            "control",
            "must differ from network.pub",
        )
        _positive(self, "sndhwm", "status_period_s")


@dataclass(frozen=True)
class EstimatorSection:
    """Force estimator (method.md): a registered kind (``bubble_rt.estimation.registry``):
    "fem" (group-lasso FEM) or "frictionless" (baseline). The parameter keys map onto
    EstimatorConfig through ``bubble_rt.estimation.estimator.CONFIG_KEYS``."""

    kind: str = "fem"
    #: Mesh preset ("coarse" 227, "medium" 390, "fine" 749 nodes) or a mesh file path.
    mesh: str = "medium"
    #: Fit the mesh onto the membrane surface seen in the reference frames.
    fit_mesh: bool = True
    #: Defaults: bubble_rt.estimation.estimator.EstimatorConfig (E fitted for the inflated model).
    k_f: float = 0.1
    k_u: float = 537592.0
    youngs_modulus: float = 0.66e6
    poisson: float = 0.5
    thickness: float = 0.65e-3
    k_const: float = 2000.0
    k_linear: float = 2.0

    def __post_init__(self) -> None:
        from bubble_rt.mesh import PRESETS

        kinds = estimator_kinds()
        _check(self.kind in kinds, "kind", "must be " + " or ".join(repr(k) for k in kinds))
        _check(bool(self.mesh), "mesh", "must name a preset or a mesh file")
        if self.mesh not in PRESETS:
            _check(
                Path(self.mesh).exists(),
                "mesh",
                f"{self.mesh!r} is neither a preset ({', '.join(PRESETS)}) nor an existing file",
            )
        for name in ESTIMATOR_RANGES:
            err = param_problem(name, getattr(self, name))
            _check(err is None, name, err or "")


@dataclass(frozen=True)
class SolverSection:
    """Real-time budget of the ADMM solver (other SolverSettings keep the core's defaults)."""

    #: Per-frame solve budget, milliseconds (0: none). The best iterate so far is published
    #: with solver status "time_limit_reached".
    time_limit_ms: float = 25.0

    def __post_init__(self) -> None:
        _non_negative(self, "time_limit_ms")


@dataclass(frozen=True)
class FlowSection:
    """Optical flow settings passed to the deformation tracker (FlowSettings; its other
    settings keep the deformation module's defaults)."""

    method: str = DEFAULT_FLOW_METHOD
    scale: float = 1.0
    forward_backward: bool = False

    def __post_init__(self) -> None:
        _check(self.method in FLOW_METHODS, "method", f"must be one of {', '.join(FLOW_METHODS)}")
        _check(0 < self.scale <= 1.0, "scale", "must be in (0, 1]")


@dataclass(frozen=True)
class ReferenceSection:
    """The untouched membrane: averaged over the first ``frames`` frames (and on tare)."""

    frames: int = 10

    def __post_init__(self) -> None:
        _positive(self, "frames")


@dataclass(frozen=True)
class ProcessingConfig:
    """Pipeline: "two_stage" overlaps the deformation of frame k+1 with the solve of frame k."""

    pipeline: str = "two_stage"
    #: Pause between two stage-one frames waiting for a newer frame, seconds.
    poll_s: float = 0.05
    #: Threads of OpenCV's parallel loops in the C++ core (OPENCV_FOR_THREADS_NUM; 0: OpenCV's
    #: default). One per stage lets the flow and the solve each keep a core instead of
    #: fighting over both. Takes effect only if the core is not loaded yet when the daemon starts.
    opencv_threads: int = 1

    def __post_init__(self) -> None:
        _check(
            self.pipeline in ("two_stage", "single"), "pipeline", "must be 'two_stage' or 'single'"
        )
        _positive(self, "poll_s")
        _check(self.opencv_threads >= 0, "opencv_threads", "must be >= 0")


@dataclass(frozen=True)
class RecordingConfig:
    """MCAP recording. ``path`` non-empty: record from start-up."""

    path: str = ""
    #: Where record_start without a path writes (timestamped file name).
    directory: str = "."
    #: Also record the input images and pressure (needed for replay), not only outputs.
    inputs: bool = True
    #: Chunk size, bytes: a crash loses at most the unflushed chunk.
    chunk_size: int = 4 * 1024 * 1024
    compression: str = "lz4"
    #: Messages waiting for the writer thread; beyond it frames are dropped from the file.
    queue: int = 64
    #: Replace an existing file at ``path`` (otherwise recording to an existing file is refused).
    overwrite: bool = False

    def __post_init__(self) -> None:
        _check(
            self.compression in ("lz4", "zstd", "none"),
            "compression",
            "must be 'lz4', 'zstd' or 'none'",
        )
        _positive(self, "chunk_size", "queue")


@dataclass(frozen=True)
class DaemonConfig:
    """The whole daemon configuration (one TOML file, one table per section)."""

    sensor_id: str = "bubble0"
    camera: CameraConfig = field(default_factory=CameraConfig)
    pressure: PressureConfig = field(default_factory=PressureConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    estimator: EstimatorSection = field(default_factory=EstimatorSection)
    solver: SolverSection = field(default_factory=SolverSection)
    flow: FlowSection = field(default_factory=FlowSection)
    reference: ReferenceSection = field(default_factory=ReferenceSection)
    processing: ProcessingConfig = field(default_factory=ProcessingConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    #: Daemon stops within this time after SIGINT/SIGTERM (threads joined, file finalised).
    shutdown_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        _check(
            bool(self.sensor_id) and all(c.isalnum() or c in "-_" for c in self.sensor_id),
            "sensor_id",
            f"must be letters, digits, '-' or '_' (it becomes a topic), got {self.sensor_id!r}",
        )
        _positive(self, "shutdown_timeout_s")

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
    def load(cls, path: str | Path) -> DaemonConfig:
        """Read and validate a TOML file."""
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError("", f"cannot read config file {p}: {exc}") from exc
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
        if not _type_ok(value, default):
            raise ConfigError(
                prefix + name,
                f"expected {type(default).__name__}, got {type(value).__name__} ({value!r})",
            )
        kwargs[name] = float(value) if isinstance(default, float) else value
    try:
        return replace(defaults, **kwargs)
    except ConfigError as exc:
        raise ConfigError(prefix + exc.key, exc.message) from None


def default_config() -> DaemonConfig:
    return DaemonConfig()
