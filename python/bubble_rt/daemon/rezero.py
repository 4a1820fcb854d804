"""Staying zeroed: the reference follows the drift while the membrane is untouched.

A real bubble drifts over hours (the camera warms the air, a little gas leaks, the LEDs warm
up), and a reference captured once reads that drift as force. While no contact has been seen
for a while, :class:`AutoZero` moves the reference (images and pressure) towards the untouched
frames: a first-order follower of time constant ``time_constant_s``, updated in steps every
``interval_s`` (each step blends the mean of the untouched frames since the last step with
weight ``1 - exp(-interval_s / time_constant_s)``).

What counts as untouched (:func:`untouched`): no contact node and no degraded reason (a frame
the daemon does not trust, e.g. a plausibility check that failed, is no evidence). A frame moves the reference only when no touched frame came within
``holdoff_s`` before *and* after it, so neither a press nor its first, not yet detected
moments, nor the membrane relaxing after it, ever enters the reference: a press held for
hours is never zeroed away.

The steps are discrete so a recording can carry them (:class:`RezeroStep`, MCAP topic
``/bubble_rt/rezero``) and a replay apply the same ones at the same frames instead of
deciding itself: the replay reproduces the live forces.

Only the deformation tracker's reference moves (a few ms); the estimator stays linearised
about the last tare's pressure (rebuilding it takes about 0.4 s).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.config import AutoZeroSection
from bubble_rt.frames import Frame

#: Untouched frames kept per interval as candidates (the rest are skipped: each holds a full
#: image pair, about 2 MB at 640 x 480).
CANDIDATES_PER_INTERVAL = 4


def untouched(contact: NDArray[np.bool_], net_force: Any, reasons: list[str]) -> bool:
    """Whether one estimated frame is evidence of the untouched membrane: no contact node, no
    degraded reason, and a finite net force. (Not a force threshold: a drift the reference
    has not caught up with, after a long press, reads as a broad force without contact, and a
    threshold would then lock re-zeroing out for good.)"""
    if reasons or bool(np.any(contact)):
        return False
    return bool(np.all(np.isfinite(np.asarray(net_force, dtype=np.float64))))


@dataclass(frozen=True)
class RezeroStep:
    """One re-zero: from frame ``first_frame_index`` on the reference is ``(1 - weight)`` times
    the previous one plus ``weight`` times the mean of frames ``frame_indices``.
    ``reference_pressure_pa``: the new reference pressure (Pa); ``drift_pa``: its change since
    the last tare (Pa); ``time_ns``: capture time of the first frame measured against it."""

    first_frame_index: int
    weight: float
    frame_indices: tuple[int, ...]
    reference_pressure_pa: float = 0.0
    drift_pa: float = 0.0
    time_ns: int = 0


class ReferenceFollower:
    """The followed reference in floating point (8-bit images would round away a slow drift:
    a step of weight w cannot move a pixel by less than 0.5 / w levels)."""

    def __init__(self, reference: Any) -> None:
        rgb, depth = getattr(reference, "rgb", None), getattr(reference, "depth", None)
        self.rgb = None if rgb is None else np.asarray(rgb, np.float32)
        self.depth = None if depth is None else np.array(depth, np.float32)
        self.pressure_pa = float(reference.pressure_pa)
        self.tare_pressure_pa = self.pressure_pa

    def step(self, frames: list[Frame], weight: float) -> Any:
        """Blend the mean of ``frames`` in with ``weight``; the new ``Reference``."""
        from bubble_rt.estimation.deformation import Reference

        mean = Reference.capture(frames)
        w = np.float32(weight)
        if self.rgb is not None and mean.rgb is not None and mean.rgb.shape == self.rgb.shape:
            self.rgb += w * (mean.rgb.astype(np.float32) - self.rgb)
        if (
            self.depth is not None
            and mean.depth is not None
            and mean.depth.shape == self.depth.shape
        ):
            # Only pixels valid in both move: the tare's holes stay holes (a pixel at a hole's
            # edge reads a mixed, millimetres-off depth now and then, never to be adopted), and
            # one the new frames miss keeps its value.
            both = (mean.depth > 0) & (self.depth > 0)
            self.depth[both] += w * (mean.depth[both] - self.depth[both])
        if math.isfinite(mean.pressure_pa):
            self.pressure_pa += float(weight) * (mean.pressure_pa - self.pressure_pa)
        rgb = None if self.rgb is None else np.clip(np.rint(self.rgb), 0, 255).astype(np.uint8)
        depth = None if self.depth is None else self.depth.copy()
        return Reference(
            rgb=rgb, depth=depth, pressure_pa=self.pressure_pa, t=mean.t, n_frames=len(frames)
        )

    @property
    def drift_pa(self) -> float:
        return self.pressure_pa - self.tare_pressure_pa


class AutoZero:
    """Decides when and from which frames to re-zero (thread-safe: stage two observes, stage
    one takes the due step and applies it before the next frame it tracks).

    Times are frame capture times (s). ``enabled`` can change at any time.
    """

    def __init__(self, section: AutoZeroSection) -> None:
        self.section = section
        self.enabled = section.enabled
        self._lock = threading.Lock()
        self._candidates: deque[Frame] = deque()
        self._evidence: list[Frame] = []
        self._last_touch = -math.inf
        self._last_step_t = -math.inf
        self._due: list[Frame] | None = None

    @property
    def weight(self) -> float:
        """The blend weight of one step, 1 - exp(-interval / time constant)."""
        s = self.section
        return 1.0 - math.exp(-s.interval_s / s.time_constant_s)

    def reset(self, t: float) -> None:
        """Forget the evidence (a tare, a new reference); nothing moves it for ``holdoff_s``."""
        with self._lock:
            self._candidates.clear()
            self._evidence = []
            self._due = None
            self._last_touch = t
            self._last_step_t = t

    def observe(self, frame: Frame, is_untouched: bool) -> None:
        """One estimated frame (stage two, in frame order)."""
        s = self.section
        t = frame.t
        with self._lock:
            if not self.enabled:
                return
            if not is_untouched:
                self._last_touch = t
                self._candidates.clear()
                self._evidence = []
                return
            spacing = s.interval_s / CANDIDATES_PER_INTERVAL
            last = self._candidates[-1].t if self._candidates else -math.inf
            if t - last >= spacing and t - self._last_touch >= s.holdoff_s:
                self._candidates.append(frame)
            # A candidate becomes evidence once holdoff_s has passed after it untouched.
            while self._candidates and t - self._candidates[0].t >= s.holdoff_s:
                self._evidence.append(self._candidates.popleft())
                del self._evidence[:-CANDIDATES_PER_INTERVAL]
            if self._evidence and t - self._last_step_t >= s.interval_s and self._due is None:
                self._due, self._evidence = self._evidence, []
                self._last_step_t = t

    def take_due(self) -> list[Frame] | None:
        """The evidence frames of a step due now (None: none), once."""
        with self._lock:
            due, self._due = self._due, None
            return due if self.enabled else None

    def set_enabled(self, enabled: bool, t: float) -> None:
        with self._lock:
            self.enabled = bool(enabled)
        if enabled:
            self.reset(t)


class RecordedRezero:
    """A replay's re-zero steps, taken from the recording instead of decided: keeps the frames
    the steps name and hands each step out before its first frame."""

    def __init__(self, steps: list[RezeroStep]) -> None:
        self.steps = deque(sorted(steps, key=lambda s: s.first_frame_index))
        self._needed = {i for s in steps for i in s.frame_indices}
        self._frames: dict[int, Frame] = {}

    def before(self, frame: Frame) -> list[tuple[RezeroStep, list[Frame]]]:
        """Steps to apply before tracking ``frame`` (with their frames); keeps ``frame`` if a
        later step names it."""
        out = []
        while self.steps and self.steps[0].first_frame_index <= frame.index:
            step = self.steps.popleft()
            frames = [self._frames.pop(i) for i in step.frame_indices if i in self._frames]
            if frames:
                out.append((step, frames))
        if frame.index in self._needed:
            self._frames[frame.index] = frame
        return out


def step_message(step: RezeroStep) -> Any:
    """The RezeroEvent protobuf of a step (recordings)."""
    from bubble_rt.io.protocol import pb

    return pb.RezeroEvent(
        time_ns=step.time_ns,
        first_frame_index=step.first_frame_index,
        weight=step.weight,
        frame_indices=list(step.frame_indices),
        reference_pressure_pa=step.reference_pressure_pa,
        drift_pa=step.drift_pa,
    )


def step_from_message(msg: Any) -> RezeroStep:
    return RezeroStep(
        first_frame_index=int(msg.first_frame_index),
        weight=float(msg.weight),
        frame_indices=tuple(int(i) for i in msg.frame_indices),
        reference_pressure_pa=float(msg.reference_pressure_pa),
        drift_pa=float(msg.drift_pa),
        time_ns=int(msg.time_ns),
    )


__all__ = [
    "AutoZero",
    "RecordedRezero",
    "ReferenceFollower",
    "RezeroStep",
    "step_from_message",
    "step_message",
    "untouched",
]
