"""Plausibility checks: a frame whose input or result the physics cannot support is marked
degraded (with a reason) instead of being published as a confident force.

Checks (each threshold is a ``[plausibility]`` or ``[pressure]`` configuration key, declared in
:mod:`bubble_rt.config`; docs/daemon.md, "Degraded frames"):

* pressure (:class:`PressureGuard`): a reading outside ``[pressure.min_pa, pressure.max_pa]``
  (absolute), or changing faster than a press can move the air (:func:`max_pressure_rate`), is
  replaced by the last good reading: the frame keeps a finite force from its dent, marked
  degraded, never one from the bad pressure.
* image (:class:`ImageGuard`): a colour image that went black or saturated (mean level), or a
  frame bit-identical to the previous one for ``frozen_frames`` frames in a row (only on a
  source whose reference frames show noise: a noise-free simulator repeats itself honestly).
* result (:func:`estimate_problems`): too few nodes tracked; a large net force with no contact
  patch.
* reference (:func:`reference_problem`): a reference pressure outside the range (e.g. 0: no
  sensor), or reference frames that do not read about zero force (a wrong camera pose,
  intrinsics or sensor profile): :class:`ReferenceRefused`, raised before any frame is
  published.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.frames import Frame, FrameError
from bubble_rt.sensor import BubblePhysics


class ReferenceRefused(FrameError):
    """The reference frames cannot be the untouched membrane (message: what to check). A
    FrameError: callers that refuse unusable reference frames refuse these too."""


@dataclass(frozen=True)
class PlausibilitySettings:
    """Thresholds of the checks (values from the configuration: ``from_config``).

    Attributes:
        min_pa, max_pa: accepted absolute pressure readings (Pa).
        max_pressure_rate_pa_s: fastest plausible pressure change (Pa/s).
        min_valid_fraction: fewest tracked nodes (fraction of all) for a healthy frame.
        dark_level, bright_level: colour image mean (0-255) below / above which it is black /
            saturated.
        frozen_frames: frames in a row bit-identical to their predecessor that mean frozen.
        max_force_without_contact_n: |net force| (N) that needs a contact patch.
        reference_max_force_n: |net force| (N) the reference frames may read.
    """

    min_pa: float
    max_pa: float
    max_pressure_rate_pa_s: float
    min_valid_fraction: float
    dark_level: float
    bright_level: float
    frozen_frames: int
    max_force_without_contact_n: float
    reference_max_force_n: float

    @classmethod
    def from_config(cls, config: Any, bubble: BubblePhysics) -> PlausibilitySettings:
        """From a ``DaemonConfig`` (its ``pressure`` and ``plausibility`` sections) and the
        sensor profile's ``bubble`` (for the pressure-rate bound)."""
        pl, pr = config.plausibility, config.pressure
        return cls(
            min_pa=float(pr.min_pa),
            max_pa=float(pr.max_pa),
            max_pressure_rate_pa_s=max_pressure_rate(bubble, float(pl.max_press_speed_m_s)),
            min_valid_fraction=float(pl.min_valid_fraction),
            dark_level=float(pl.dark_level),
            bright_level=float(pl.bright_level),
            frozen_frames=int(pl.frozen_frames),
            max_force_without_contact_n=float(pl.max_force_without_contact_n),
            reference_max_force_n=float(pl.reference_max_force_n),
        )


# ------------------------------------------------------------------------------ physics
def footprint_area(bubble: BubblePhysics) -> float:
    """Area (m^2) of the bubble's elliptic rim: the most membrane an object can push."""
    return math.pi * bubble.semi_axis_x_m * bubble.semi_axis_y_m


def dome_volume(bubble: BubblePhysics) -> float:
    """Air volume (m^3) under the inflated dome (half an ellipsoid over the rim)."""
    return 2.0 / 3.0 * footprint_area(bubble) * bubble.dome_height_m


def max_pressure_rate(bubble: BubblePhysics, press_speed_m_s: float) -> float:
    """Fastest pressure rise (Pa/s) a press can make: the whole footprint pushed in at
    ``press_speed_m_s`` sweeps ``footprint * speed`` m^3/s out of the air volume (chamber plus
    dome), and isothermal air raises its pressure by ``p dV / V`` (p the rest pressure)."""
    air = bubble.chamber_volume_m3 + dome_volume(bubble)
    return bubble.rest_pressure_pa * footprint_area(bubble) * press_speed_m_s / air


# ------------------------------------------------------------------------------ pressure
def capture_time(frame: Frame) -> float:
    """When ``frame`` was captured (s): a replayed or simulated frame is restamped on delivery
    (two may leave 1 ms apart), its own time kept in ``meta["source_t"]``; its pressure
    belongs to that time."""
    return float(frame.meta.get("source_t", frame.t))


class PressureGuard:
    """Holds the last good pressure; a reading out of range or jumping faster than
    ``max_pressure_rate_pa_s`` since it is replaced by it (with a reason)."""

    def __init__(self, settings: PlausibilitySettings, pressure_pa: float, t: float) -> None:
        """``pressure_pa`` at time ``t`` (s): the reference's, the first good reading."""
        self.s = settings
        self.good_pa, self.good_t = float(pressure_pa), float(t)

    def check(self, t: float, pressure_pa: float) -> tuple[float, list[str]]:
        """(pressure to use, Pa; reasons) for a reading ``pressure_pa`` at time ``t`` (s)."""
        s, p = self.s, float(pressure_pa)
        held = f"held at the last good {self.good_pa:.0f} Pa"
        if not (math.isfinite(p) and s.min_pa <= p <= s.max_pa):
            return self.good_pa, [
                f"pressure {p:.6g} Pa outside [{s.min_pa:g}, {s.max_pa:g}] Pa "
                f"(pressure.min_pa, max_pa): {held}"
            ]
        dt = t - self.good_t
        if dt > 0 and abs(p - self.good_pa) > s.max_pressure_rate_pa_s * dt:
            return self.good_pa, [
                f"pressure jumped {p - self.good_pa:+.0f} Pa in {dt * 1e3:.0f} ms, faster than "
                f"a press can move the air ({s.max_pressure_rate_pa_s * dt:.0f} Pa; "
                f"plausibility.max_press_speed_m_s): {held}"
            ]
        # dt <= 0: time went back (a replay looped, frames out of order): a new baseline.
        self.good_pa, self.good_t = p, float(t)
        return p, []


# ------------------------------------------------------------------------------ images
def _images_equal(a: Frame, b: Frame) -> bool:
    """Colour and depth bit-identical (None equals None)."""
    pairs: tuple[tuple[Any, Any], ...] = ((a.rgb, b.rgb), (a.depth, b.depth))
    return all(_bit_identical(x, y) for x, y in pairs)


#: bytes compared before the rest of an image (two rows of a 640-pixel RGB image)
_HEAD_BYTES = 4096


def _bit_identical(x: Any, y: Any) -> bool:
    """Same shape, dtype and bytes (None equals None). A frozen source repeats its bytes, NaN
    holes included (np.array_equal never finds NaN equal to itself). A live camera's noise
    differs within its first rows, so those are compared first and the rest only if equal."""
    if x is None or y is None:
        return x is y
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape or x.dtype != y.dtype:
        return False
    xb, yb = (np.ascontiguousarray(a).reshape(-1).view(np.uint8) for a in (x, y))
    head = min(xb.size, _HEAD_BYTES)
    return bool(np.array_equal(xb[:head], yb[:head]) and np.array_equal(xb[head:], yb[head:]))


def noisy_source(frames: list[Frame]) -> bool:
    """True when consecutive untouched ``frames`` differ (a camera with noise): only then can
    a frame identical to its predecessor mean a frozen source."""
    return any(not _images_equal(a, b) for a, b in zip(frames, frames[1:], strict=False))


class ImageGuard:
    """Black, saturated or frozen colour images."""

    def __init__(self, settings: PlausibilitySettings, *, frozen_check: bool) -> None:
        self.s = settings
        self.frozen_check = frozen_check
        self._prev: Frame | None = None
        self._same = 0

    def check(self, frame: Frame) -> list[str]:
        """Degraded reasons for ``frame`` (empty when its images look alive)."""
        s, out = self.s, []
        if frame.rgb is not None:
            # every fourth row, summed as integers per row (no overflow below 16 MB a row):
            # a third of the time of a float mean over a strided sample
            rows = np.asarray(frame.rgb)[::4]
            per_row = rows.reshape(len(rows), -1).sum(axis=1, dtype=np.uint32)
            level = float(per_row.sum(dtype=np.uint64)) / max(rows.size, 1)
            if level < s.dark_level:
                out.append(
                    f"colour image black (mean level {level:.1f} < plausibility.dark_level "
                    f"{s.dark_level:g}): lens covered or lights off?"
                )
            elif level > s.bright_level:
                out.append(
                    f"colour image saturated (mean level {level:.1f} > plausibility."
                    f"bright_level {s.bright_level:g})"
                )
        if self.frozen_check:
            prev, self._prev = self._prev, frame
            self._same = self._same + 1 if prev is not None and _images_equal(prev, frame) else 0
            if self._same >= s.frozen_frames:
                out.append(
                    f"images frozen: {self._same} frames in a row bit-identical "
                    f"(plausibility.frozen_frames {s.frozen_frames})"
                )
        return out


# ------------------------------------------------------------------------------ results
def estimate_problems(
    settings: PlausibilitySettings,
    valid_fraction: float,
    net_force: NDArray[np.float64],
    contact: NDArray[np.bool_],
) -> list[str]:
    """Degraded reasons of a solved frame: too few nodes tracked; a large net force (N) with
    no contact node."""
    s, out = settings, []
    if not valid_fraction >= s.min_valid_fraction:
        out.append(
            f"only {valid_fraction:.0%} of nodes tracked (plausibility.min_valid_fraction "
            f"{s.min_valid_fraction:g})"
        )
    f = float(np.linalg.norm(np.nan_to_num(np.asarray(net_force, np.float64), posinf=1e300)))
    if f > s.max_force_without_contact_n and not np.asarray(contact, bool).any():
        out.append(
            f"net force {f:.3g} N with no contact patch (plausibility."
            f"max_force_without_contact_n {s.max_force_without_contact_n:g} N)"
        )
    return out


def reference_pressure_problem(settings: PlausibilitySettings, pressure_pa: float) -> str:
    """Why a reference pressure (Pa) cannot be the rest pressure, else ""."""
    s, p = settings, float(pressure_pa)
    if math.isfinite(p) and s.min_pa <= p <= s.max_pa:
        return ""
    return (
        f"reference refused: its pressure {p:.6g} Pa is outside [{s.min_pa:g}, {s.max_pa:g}] Pa "
        "(pressure.min_pa, max_pa): check the pressure source and its unit (0 Pa: no reading)"
    )


def reference_force_problem(settings: PlausibilitySettings, forces_n: list[float]) -> str:
    """Why untouched reference frames reading ``forces_n`` (|net force|, N) cannot be the
    untouched membrane, else ""."""
    worst = max(forces_n, default=0.0)
    if worst <= settings.reference_max_force_n:
        return ""
    return (
        f"reference refused: the untouched reference frames read up to {worst:.3g} N "
        f"(plausibility.reference_max_force_n {settings.reference_max_force_n:g} N), so the "
        "membrane the camera sees is not where the model puts it. Check the camera pose "
        "(a ROS 2 bag without /tf_static gets the Punyo pose), the intrinsics (camera_info) "
        "and the sensor profile (estimator.profile); or something touched the membrane"
    )


__all__ = [
    "ImageGuard",
    "PlausibilitySettings",
    "PressureGuard",
    "ReferenceRefused",
    "capture_time",
    "dome_volume",
    "estimate_problems",
    "footprint_area",
    "max_pressure_rate",
    "noisy_source",
    "reference_force_problem",
    "reference_pressure_problem",
]
