"""Sensor frames: what one camera exposure plus the matching pressure reading carry.

Units: RGB H x W x 3 uint8 (RGB order); depth H x W float32 metres of camera z, 0 where invalid;
pressure in pascals (absolute or gauge, as long as the reference uses the same); times in
seconds (any monotonic clock shared by the sources).

Frames validate themselves on construction (shapes, dtypes, matching image sizes, finite
pressure, not all depth invalid) and raise :class:`FrameError` naming the field at fault.
``Frame.validate(camera)`` additionally checks the image size against a camera. Constructors
build frames from an organised point cloud (``from_pointcloud``) or a 16-bit depth image with a
scale (``from_uint16``); both take the pressure with an explicit unit ("Pa", "hPa", "kPa").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from bubble_rt.camera import Camera

HPA = 100.0  # pascals per hectopascal

#: Pascals per unit for the pressure units frames accept.
PRESSURE_UNITS: dict[str, float] = {"Pa": 1.0, "hPa": HPA, "kPa": 1000.0, "mbar": HPA}


#: What a skipped frame or reading was counted under (:attr:`FrameFault.kind`): the colour
#: image, the depth image, the pressure reading, or the frame as a whole (a file that cannot
#: be read, images of different sizes, an estimate that failed).
FAULT_KINDS = ("colour", "depth", "pressure", "frame")


class FrameError(ValueError):
    """A frame is malformed; the message names the field at fault, ``kind`` (one of
    :data:`FAULT_KINDS`) says which part of the frame it is."""

    def __init__(self, message: str = "", kind: str = "frame") -> None:
        super().__init__(message)
        self.kind = kind if kind in FAULT_KINDS else "frame"


def pressure_to_pa(value: float, unit: str) -> float:
    """Convert a pressure reading to pascals; ``unit`` is one of PRESSURE_UNITS."""
    if unit not in PRESSURE_UNITS:
        raise FrameError(f"pressure unit {unit!r} unknown; use one of {sorted(PRESSURE_UNITS)}")
    p = (
        float(np.asarray(value, dtype=np.float64).reshape(-1)[0])
        if np.ndim(value)
        else float(value)
    )
    if not np.isfinite(p):
        raise FrameError(f"pressure is not finite: {value!r}", "pressure")
    return p * PRESSURE_UNITS[unit]


@dataclass
class Frame:
    """One synchronised sensor sample.

    Attributes:
        rgb: H x W x 3 uint8 colour image (RGB order), or None (oracle frames from the simulator).
        depth: H x W float32 depth (metres, camera z), 0 where invalid, or None.
        pressure_pa: air pressure, pascals.
        t: capture time of the camera frame, seconds.
        t_pressure: time of the pressure reading, seconds (None: same as ``t``).
        wrench: ground-truth [fx, fy, fz, tx, ty, tz] from a force/torque sensor (N, N m), or None.
        truth: simulator ground truth (``bubble_rt.sim.GroundTruth``), or None.
        index: sequence number within its source.
        meta: free-form extras (e.g. degraded reasons, source name).
    """

    rgb: NDArray[np.uint8] | None
    depth: NDArray[np.float32] | None
    pressure_pa: float
    t: float = 0.0
    t_pressure: float | None = None
    wrench: NDArray[np.float64] | None = None
    truth: Any = None
    index: int = 0
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.rgb is not None:
            rgb = np.asarray(self.rgb)
            if rgb.ndim != 3 or rgb.shape[2] != 3:
                raise FrameError(f"rgb must be H x W x 3, got shape {rgb.shape}", "colour")
            if rgb.dtype != np.uint8:
                raise FrameError(f"rgb must be uint8, got dtype {rgb.dtype}", "colour")
            self.rgb = rgb
        if self.depth is not None:
            d = np.asarray(self.depth)
            if d.ndim != 2:
                raise FrameError(f"depth must be H x W, got shape {d.shape}", "depth")
            if not np.issubdtype(d.dtype, np.floating):
                raise FrameError(
                    f"depth must be float metres, got dtype {d.dtype} "
                    "(use Frame.from_uint16 for 16-bit depth with a scale)",
                    "depth",
                )
            d = d.astype(np.float32, copy=False)
            if not np.any(d > 0):  # NaN compares False: all-NaN is all-invalid too
                raise FrameError("depth has no valid pixel (all zero, negative or NaN)", "depth")
            self.depth = d
        if self.rgb is not None and self.depth is not None:
            if self.rgb.shape[:2] != self.depth.shape:
                raise FrameError(
                    f"rgb size {self.rgb.shape[1]} x {self.rgb.shape[0]} differs from depth size "
                    f"{self.depth.shape[1]} x {self.depth.shape[0]}"
                )
        try:
            p = float(self.pressure_pa)
        except (TypeError, ValueError) as exc:
            raise FrameError(
                f"pressure_pa must be a number, got {self.pressure_pa!r}", "pressure"
            ) from exc
        if not np.isfinite(p):
            raise FrameError(f"pressure_pa is not finite: {p}", "pressure")
        self.pressure_pa = p
        if self.wrench is not None:
            w = np.asarray(self.wrench, dtype=np.float64).reshape(-1)
            if w.shape != (6,):
                raise FrameError(f"wrench must have 6 components, got {w.size}")
            self.wrench = w

    @property
    def shape(self) -> tuple[int, int] | None:
        """(H, W) of the images, or None when the frame has none."""
        img = self.rgb if self.rgb is not None else self.depth
        return None if img is None else (int(img.shape[0]), int(img.shape[1]))

    def validate(self, camera: Camera | None = None, *, need_images: bool = False) -> Frame:
        """Check the frame against a camera (image size) and return it.

        Raises FrameError naming the field when the rgb or depth size differs from the camera's
        width x height, or when ``need_images`` and rgb or depth is missing.
        """
        if need_images:
            for name in ("rgb", "depth"):
                if getattr(self, name) is None:
                    raise FrameError(f"{name} is missing (this stage needs camera images)")
        if camera is not None:
            want = (camera.height, camera.width)
            for name in ("rgb", "depth"):
                img = getattr(self, name)
                if img is not None and tuple(img.shape[:2]) != want:
                    raise FrameError(
                        f"{name} size {img.shape[1]} x {img.shape[0]} differs from the camera's "
                        f"{camera.width} x {camera.height}",
                        "colour" if name == "rgb" else "depth",
                    )
        return self

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_pointcloud(
        cls,
        rgb: NDArray[np.uint8] | None,
        points: NDArray,
        pressure: float,
        camera: Camera,
        *,
        pressure_unit: str = "Pa",
        max_depth_m: float | None = 2.0,
        **fields: Any,
    ) -> Frame:
        """A frame from an organised point cloud.

        Args:
            rgb: H x W x 3 uint8 RGB image aligned with the cloud, or None.
            points: (H*W) x 3 (or H x W x 3) camera-frame points, metres, row-major pixels;
                points that are all zero or non-finite are invalid.
            pressure: pressure reading in ``pressure_unit``.
            camera: gives H and W (``camera.height``, ``camera.width``).
            max_depth_m: depths beyond this are invalid (sensors saturate, e.g. 6.5535 m);
                None keeps all.
            **fields: further Frame fields (t, t_pressure, wrench, index, meta, truth).
        """
        h, w = camera.height, camera.width
        pts = np.asarray(points)
        if pts.ndim == 3:
            pts = pts.reshape(-1, pts.shape[-1])
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise FrameError(
                f"point cloud must be (H*W) x 3, got shape {np.shape(points)}", "depth"
            )
        if pts.shape[0] != h * w:
            raise FrameError(
                f"point cloud has {pts.shape[0]} points; the camera's {w} x {h} needs {h * w}",
                "depth",
            )
        z = pts[:, 2].astype(np.float32)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(pts).all(axis=1) & (z > 0)
            if max_depth_m is not None:
                ok &= z < max_depth_m
        depth = np.where(ok, z, np.float32(0)).reshape(h, w)
        if not ok.any():
            raise FrameError(
                "point cloud has no valid point (all zero, NaN or beyond max depth)", "depth"
            )
        p = pressure_to_pa(pressure, pressure_unit)
        return cls(rgb=rgb, depth=depth, pressure_pa=p, **fields).validate(camera)

    @classmethod
    def from_uint16(
        cls,
        rgb: NDArray[np.uint8] | None,
        depth: NDArray[np.uint16],
        depth_scale: float,
        pressure: float,
        *,
        pressure_unit: str = "Pa",
        camera: Camera | None = None,
        **fields: Any,
    ) -> Frame:
        """A frame from a 16-bit depth image; metres = raw * ``depth_scale`` (0 = invalid).

        RealSense cameras default to ``depth_scale`` = 0.001 (millimetres) and the D405 to 1e-4.
        """
        d = np.asarray(depth)
        if d.dtype != np.uint16:
            raise FrameError(f"depth must be uint16 for from_uint16, got dtype {d.dtype}")
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise FrameError(f"depth_scale must be positive metres per unit, got {depth_scale}")
        metres = d.astype(np.float32) * np.float32(depth_scale)
        p = pressure_to_pa(pressure, pressure_unit)
        frame = cls(rgb=rgb, depth=metres, pressure_pa=p, **fields)
        return frame.validate(camera)


@dataclass(frozen=True)
class FrameFault:
    """A frame (or a reading) of a recording that could not be used: every reader yields one
    in its place, and consumers skip, count (per ``kind``) and name it.

    ``index`` is the frame's position in the recording (a reading's position in its stream for
    ``kind == "pressure"`` readings), ``where`` names the recording's file and the frame,
    ``reason`` says what is wrong (truncated file, wrong shape or dtype, no valid depth, NaN
    pressure, ...), ``kind`` is one of :data:`FAULT_KINDS`.
    """

    index: int
    where: str
    reason: str
    kind: str = "frame"
    #: A reading of a stream the frames interpolate (a bag's pressure): skipping it costs no
    #: frame.
    reading: bool = False

    def __str__(self) -> str:
        return f"{self.where}: {self.reason}"

    def as_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "kind": self.kind,
            "reading": self.reading,
            "where": self.where,
            "reason": self.reason,
        }


def fault_of(exc: BaseException, index: int, where: str) -> FrameFault:
    """The FrameFault for a frame whose reading raised ``exc``: a FrameError keeps its
    message and kind, any other exception (a reshape of a truncated buffer, a damaged file's
    decoder) is named by its type."""
    if isinstance(exc, FrameError):
        return FrameFault(index, where, str(exc), exc.kind)
    return FrameFault(index, where, f"{type(exc).__name__}: {exc}")


def tolerant(index: int, where: str, load: Callable[[], Frame]) -> Frame | FrameFault:
    """``load()``, or the FrameFault saying why it failed: the one way every recording layout
    (Punyo and PNG folders, ROS 2 bags, MCAP) turns a bad frame into a skipped one."""
    try:
        return load()
    except Exception as exc:  # any damage to one frame ends that frame only
        return fault_of(exc, index, where)


class FaultTally:
    """Skipped frames and readings of a run: counts per kind and the faults themselves
    (the first ``keep``, so a recording that is all damage cannot exhaust memory)."""

    def __init__(self, keep: int = 1000) -> None:
        self.counts: dict[str, int] = {}
        self.faults: list[FrameFault] = []
        self.keep = keep

    def add(self, fault: FrameFault) -> None:
        self.counts[fault.kind] = self.counts.get(fault.kind, 0) + 1
        if len(self.faults) < self.keep:
            self.faults.append(fault)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def summary(self) -> str:
        """ "3 skipped (depth 2, pressure 1)", or "" when nothing was skipped."""
        if not self.counts:
            return ""
        parts = ", ".join(f"{k} {n}" for k, n in sorted(self.counts.items()))
        return f"{self.total} skipped ({parts})"
