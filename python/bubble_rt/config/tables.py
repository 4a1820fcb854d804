"""The sections of the daemon configuration: one frozen dataclass per TOML table, every key
declared with :func:`~bubble_rt.config.options.option`, cross-key rules in ``__post_init__``.

:class:`~bubble_rt.config.DaemonConfig` gathers them; import everything from
:mod:`bubble_rt.config`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bubble_rt._validate import ParamRange, PathError, regular_file, zmq_endpoint_problem
from bubble_rt.config.options import ConfigError, _check, _field, check_fields, key_range, option
from bubble_rt.estimation.names import (
    DEFAULT_FLOW_METHOD,
    DEFAULT_REFINE_WINDOW_PX,
    FLOW_METHODS,
    refine_window_problem,
)
from bubble_rt.estimation.params import ESTIMATOR_PARAMS, FLOW_SCALE
from bubble_rt.estimation.registry import estimator_kinds
from bubble_rt.io.codec_names import COLOR_CODECS
from bubble_rt.sensor import PROFILES, SensorProfile, profile_for_layout

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
    support_tol: float = _estimator_option("support_tol")
    peak_radius_m: float = _estimator_option("peak_radius_m")
    nonlinear_iterations: int = _estimator_option("nonlinear_iterations")
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
    refine_window_px: int = option(
        DEFAULT_REFINE_WINDOW_PX,
        "window of the Lucas-Kanade refinement of the flow at each node, started from the "
        "dense flow (odd); 0: the dense flow as sampled",
        lo=0,
        hi=63,
        unit="px",
    )

    def __post_init__(self) -> None:
        check_fields(self)
        problem = refine_window_problem(self.refine_window_px)
        if problem is not None:
            raise ConfigError("refine_window_px", problem)


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
        0,
        "threads of OpenCV's parallel loops in the C++ core (the optical flow; set with "
        "cv::setNumThreads when the daemon starts; 0: OpenCV's default, every core)",
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
