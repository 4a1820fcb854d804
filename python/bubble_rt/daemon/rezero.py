"""Staying zeroed: what the daemon measures against follows the drift while untouched.

A real bubble drifts over hours (the camera warms the air, a little gas leaks, the LEDs warm
up), and a reference captured once reads that drift as force. While no contact has been seen
for a while, the reference follows the untouched frames (:class:`Rezeroing`, the daemon's
part): a first-order follower of time constant ``time_constant_s``, updated in steps every
``interval_s``, each blending the evidence since the last step with weight
``1 - exp(-interval_s / time_constant_s)`` (:class:`AutoZero` decides, stage two).

What counts as untouched (:func:`untouched`): no contact node and no degraded reason (a frame
the daemon does not trust, e.g. a plausibility check that failed, is no evidence). A frame
moves the reference only when no touched frame came within ``holdoff_s`` before *and* after
it, so neither a press nor its first, not yet detected moments, nor the membrane relaxing
after it, ever enters the reference: a press held for hours is never zeroed away.

What follows is what the tracker measures against (:class:`ReferenceFollower`): the pressure,
the node positions (an offset from the tare's mesh) and the flow's reference image (the tare's
with the LEDs' gain and offset). A step takes a few ms; the mesh and the estimator stay those
of the last tare (the estimator is linearised about its pressure: rebuilding it takes about
0.4 s).

The steps are discrete so a recording can carry them (:class:`RezeroStep`, MCAP topic
``/bubble_rt/rezero``, with the state they set, and the state at the start of the recording)
and a replay set the same states at the same frames instead of deciding itself
(:class:`RecordedRezero`): the replay reproduces the live forces, however the recording was
started.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.config import AutoZeroSection
from bubble_rt.frames import Frame

#: Untouched frames kept per interval as candidates (the rest are skipped: each holds its
#: colour image, about 0.9 MB at 640 x 480).
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
    """One re-zero: from frame ``first_frame_index`` on the daemon measures against the state
    (``reference_pressure_pa``, ``gain``, ``bias``, ``offset``: see :class:`ReferenceFollower`),
    blended with ``weight`` from the untouched frames ``frame_indices`` (weight 0, no frames:
    the state when a recording starts). ``drift_pa``: the pressure's change since the last
    tare (Pa); ``time_ns``: capture time of the first frame measured against it."""

    first_frame_index: int
    weight: float
    frame_indices: tuple[int, ...]
    reference_pressure_pa: float
    gain: float
    bias: float
    offset: NDArray[np.float64] | None
    drift_pa: float = 0.0
    time_ns: int = 0


#: One piece of evidence: an untouched frame and its node displacements from the tare's mesh
#: (N x 3, m; None when the processor gives none).
Evidence = tuple[Frame, NDArray[np.float64] | None]


class ReferenceFollower:
    """The followed reference, in floating point (an 8-bit image or a rounded step would stall
    a slow drift: a step of weight w cannot move a value by less than its rounding / w).

    What the tracker measures against, and so what follows: the pressure (dp), the node
    positions (a warmer gas bulges the membrane: the mean displacement of the untouched frames
    from the tare's mesh, ``offset``) and the flow's reference image, as the tare's image under
    the current illumination (a gain and an offset matched to the untouched frames' mean and
    spread: the LEDs' drift, without moving the texture, which the offset accounts for).
    """

    def __init__(self, reference: Any) -> None:
        self.tare = reference
        rgb = getattr(reference, "rgb", None)
        self._tare_rgb = None if rgb is None else np.asarray(rgb, np.float32)
        self.gain = 1.0
        self.bias = 0.0
        self.pressure_pa = float(reference.pressure_pa)
        self.tare_pressure_pa = self.pressure_pa
        self.offset: NDArray[np.float64] | None = None

    def step(self, evidence: list[Evidence], weight: float) -> tuple[Any, Any]:
        """Blend the evidence in with ``weight``; (the new ``Reference``, node offset)."""
        w = float(weight)
        frames = [f for f, _ in evidence]
        p = float(np.mean([f.pressure_pa for f in frames]))
        if math.isfinite(p):
            self.pressure_pa += w * (p - self.pressure_pa)
        us = [u for _, u in evidence if u is not None]
        if us:
            mean_u = np.mean(np.stack(us), axis=0)
            if np.isfinite(mean_u).all():
                base = self.offset if self.offset is not None else np.zeros_like(mean_u)
                self.offset = base + w * (mean_u - base)
        tare = self._tare_rgb
        if tare is not None:
            imgs = [f.rgb for f in frames if f.rgb is not None and f.rgb.shape == tare.shape]
            if imgs:
                mean = np.mean([np.asarray(i[::4, ::4], np.float32) for i in imgs], axis=0)
                x = tare[::4, ::4]
                sx = float(x.std())
                if sx > 1e-3:
                    gain = float(mean.std()) / sx
                    bias = float(mean.mean()) - gain * float(x.mean())
                    self.gain += w * (gain - self.gain)
                    self.bias += w * (bias - self.bias)
        return self.reference(), self.offset_copy()

    def reference(self) -> Any:
        """The ``Reference`` of the current state (the tare's depth: the tracker reads node
        positions from the depth of each frame, not from the reference's)."""
        from bubble_rt.estimation.deformation import Reference

        rgb = None
        if self._tare_rgb is not None:
            rgb = np.clip(np.rint(self.gain * self._tare_rgb + self.bias), 0, 255)
            rgb = rgb.astype(np.uint8)
        return Reference(
            rgb=rgb,
            depth=getattr(self.tare, "depth", None),
            pressure_pa=self.pressure_pa,
            t=float(getattr(self.tare, "t", 0.0)),
            n_frames=int(getattr(self.tare, "n_frames", 1)),
        )

    def offset_copy(self) -> NDArray[np.float64] | None:
        return None if self.offset is None else self.offset.copy()

    def set_state(self, step: RezeroStep) -> bool:
        """Take a recorded step's state (a replay); False when it is the current one (the
        start of a recording made before any re-zero: nothing to change)."""
        offset = None if step.offset is None else np.array(step.offset, np.float64)
        same = (
            self.pressure_pa == step.reference_pressure_pa
            and self.gain == step.gain
            and self.bias == step.bias
            and (
                (offset is None and self.offset is None)
                or (
                    offset is not None
                    and self.offset is not None
                    and np.array_equal(offset, self.offset)
                )
            )
        )
        self.pressure_pa = float(step.reference_pressure_pa)
        self.gain, self.bias = float(step.gain), float(step.bias)
        self.offset = offset
        return not same

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
        self._candidates: deque[Evidence] = deque()
        self._evidence: list[Evidence] = []
        self._last_touch = -math.inf
        self._last_step_t = -math.inf
        self._due: list[Evidence] | None = None

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

    def observe(self, frame: Frame, is_untouched: bool, displacements: Any = None) -> None:
        """One estimated frame (stage two, in frame order); ``displacements``: its nodes'
        displacements from the tare's mesh (N x 3, m) when the processor measures them."""
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
            last = self._candidates[-1][0].t if self._candidates else -math.inf
            if t - last >= spacing and t - self._last_touch >= s.holdoff_s:
                # Only the colour image, pressure and displacements are used: keep no more.
                light = replace(frame, depth=None, truth=None, wrench=None)
                self._candidates.append((light, displacements))
            # A candidate becomes evidence once holdoff_s has passed after it untouched.
            while self._candidates and t - self._candidates[0][0].t >= s.holdoff_s:
                self._evidence.append(self._candidates.popleft())
                del self._evidence[:-CANDIDATES_PER_INTERVAL]
            if self._evidence and t - self._last_step_t >= s.interval_s and self._due is None:
                self._due, self._evidence = self._evidence, []
                self._last_step_t = t

    def take_due(self) -> list[Evidence] | None:
        """The evidence of a step due now (None: none), once."""
        with self._lock:
            due, self._due = self._due, None
            return due if self.enabled else None

    def set_enabled(self, enabled: bool, t: float) -> None:
        with self._lock:
            self.enabled = bool(enabled)
        if enabled:
            self.reset(t)


class RecordedRezero:
    """A replay's re-zero steps, taken from the recording instead of decided: each recorded
    state is set before the frame it was first used for."""

    def __init__(self, steps: list[RezeroStep]) -> None:
        self.steps = deque(sorted(steps, key=lambda s: s.first_frame_index))

    def before(self, frame: Frame) -> list[RezeroStep]:
        """Steps to apply before tracking ``frame`` (the last one wins)."""
        out = []
        while self.steps and self.steps[0].first_frame_index <= frame.index:
            out.append(self.steps.popleft())
        return out


class Rezeroing:
    """The daemon's re-zeroing, all in one place: the decisions (:class:`AutoZero`, stage two
    observes), the followed state (:class:`ReferenceFollower`), the steps applied before stage
    one tracks a frame (decided, or a replay's recorded ones), their recording, and what the
    status reports. ``on_error(kind, exc)``: the daemon's fault counter."""

    def __init__(
        self, section: AutoZeroSection, on_error: Callable[[str, BaseException | str], None]
    ) -> None:
        self.autozero = AutoZero(section)
        self.follower: ReferenceFollower | None = None
        self.recorded: RecordedRezero | None = None
        self.count = 0
        self.last_ns = 0
        self._on_error = on_error
        self._anchor = False

    # ------------------------------------------------------------------ state
    @property
    def enabled(self) -> bool:
        return self.autozero.enabled

    def set_enabled(self, enabled: bool) -> None:
        """Control request ``set_auto_zero``; turning it on starts a fresh hold-off."""
        self.autozero.set_enabled(enabled, time.time())

    @property
    def drift_pa(self) -> float:
        """The pressure drift followed since the last tare (Pa)."""
        return self.follower.drift_pa if self.follower is not None else 0.0

    def use_recording(self, messages: list[Any] | None) -> None:
        """A replay of this project's recording (its RezeroEvent messages, None: not one):
        set the live run's states at the same frames, and decide nothing."""
        if messages is not None:
            self.recorded = RecordedRezero([step_from_message(m) for m in messages])
            self.autozero.enabled = False

    def tare(self, processor: Any, t: float) -> None:
        """A new reference was installed (start, tare): follow from it, drift 0."""
        ref = getattr(processor, "reference", None)
        self.follower = ReferenceFollower(ref) if hasattr(ref, "pressure_pa") else None
        self.autozero.reset(t)

    def recording_started(self) -> None:
        """The next recorded frame is preceded by the current state (weight 0)."""
        self._anchor = True

    # ------------------------------------------------------------------ per frame
    def before(self, frame: Frame, processor: Any, recorder: Any) -> None:
        """Stage one, before tracking (and recording) ``frame``: apply the step due, if any,
        and write the state a just-started recording begins with."""
        if self.follower is not None and hasattr(processor, "follow_reference"):
            if self.recorded is not None:
                steps = self.recorded.before(frame)
                if steps and self.follower.set_state(steps[-1]):
                    self._follow(frame, processor, recorder, steps[-1].weight, ())
            else:
                due = self.autozero.take_due()
                if due:
                    try:
                        self.follower.step(due, self.autozero.weight)
                    except Exception as exc:
                        self._on_error("rezero", exc)
                    else:
                        idx = tuple(f.index for f, _ in due)
                        self._follow(frame, processor, recorder, self.autozero.weight, idx)
        if recorder is not None and self._anchor:
            self._anchor = False
            self._record(recorder, 0.0, (), frame)

    def displacements(self, data: Any) -> Any:
        """Stage one's node displacements measured from the tare's mesh (the tracker measures
        them from the nodes moved by the followed offset): evidence for :meth:`observe`."""
        u = getattr(data, "U", None)
        if u is None:
            return None
        off = self.follower.offset if self.follower is not None else None
        return u + off if off is not None else u

    def observe(
        self, frame: Frame, contact: Any, net_force: Any, reasons: list[str], displacements: Any
    ) -> None:
        """Stage two, after estimating ``frame``."""
        self.autozero.observe(frame, untouched(contact, net_force, reasons), displacements)

    def _follow(
        self, frame: Frame, processor: Any, recorder: Any, weight: float, idx: tuple[int, ...]
    ) -> None:
        f = self.follower
        assert f is not None
        try:
            ok = bool(processor.follow_reference(f.reference(), f.offset_copy()))
        except Exception as exc:
            self._on_error("rezero", exc)
            return
        if not ok:
            self._on_error("rezero", "this estimator kind cannot follow a reference; turned off")
            self.autozero.enabled = False
            return
        self.count += 1
        self.last_ns = int(round(frame.t * 1e9))
        if recorder is not None and not self._anchor:
            self._record(recorder, weight, idx, frame)

    def _record(self, recorder: Any, weight: float, idx: tuple[int, ...], frame: Frame) -> None:
        from bubble_rt.io.mcap import TOPIC_REZERO

        f = self.follower
        if f is None:
            return
        step = RezeroStep(
            first_frame_index=frame.index,
            weight=weight,
            frame_indices=idx,
            reference_pressure_pa=f.pressure_pa,
            gain=f.gain,
            bias=f.bias,
            offset=f.offset,
            drift_pa=f.drift_pa,
            time_ns=int(round(frame.t * 1e9)),
        )
        recorder.write_message(TOPIC_REZERO, step_message(step), frame.t, frame.index)


def step_message(step: RezeroStep) -> Any:
    """The RezeroEvent protobuf of a step (recordings)."""
    from bubble_rt.io.protocol import pb

    off = [] if step.offset is None else np.asarray(step.offset, np.float64).ravel().tolist()
    return pb.RezeroEvent(
        time_ns=step.time_ns,
        first_frame_index=step.first_frame_index,
        weight=step.weight,
        frame_indices=list(step.frame_indices),
        reference_pressure_pa=step.reference_pressure_pa,
        drift_pa=step.drift_pa,
        gain=step.gain,
        bias=step.bias,
        node_offset=off,
    )


def step_from_message(msg: Any) -> RezeroStep:
    off = np.asarray(msg.node_offset, np.float64)
    return RezeroStep(
        first_frame_index=int(msg.first_frame_index),
        weight=float(msg.weight),
        frame_indices=tuple(int(i) for i in msg.frame_indices),
        reference_pressure_pa=float(msg.reference_pressure_pa),
        gain=float(msg.gain),
        bias=float(msg.bias),
        offset=off.reshape(-1, 3) if off.size and off.size % 3 == 0 else None,
        drift_pa=float(msg.drift_pa),
        time_ns=int(msg.time_ns),
    )


__all__ = [
    "AutoZero",
    "Rezeroing",
    "RecordedRezero",
    "ReferenceFollower",
    "Evidence",
    "RezeroStep",
    "step_from_message",
    "step_message",
    "untouched",
]
