"""The real-time pipeline, wired in one place: capture -> reference -> fitted mesh -> deformation
tracker -> estimator.

``Pipeline.process(frame)`` runs it all; the daemon calls the two stages itself,
``deform(frame)`` (optical flow + lifting -> ``Deformation``) and ``solve(frame, deformation)``
(solve + post -> ``Estimate``), so that the flow of frame k+1 overlaps the solve of frame k.
Estimator kinds come from :mod:`bubble_rt.estimation.registry`, trackers from
:func:`bubble_rt.estimation.deformation.make_tracker` (the simulator registers "oracle").
The paper-faithful reference pipeline (:mod:`bubble_rt.reference`) is separate on purpose.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from bubble_rt.camera import Camera
from bubble_rt.estimation.deformation import (
    Deformation,
    FlowSettings,
    Reference,
    Tracker,
    make_tracker,
)
from bubble_rt.estimation.estimator import EstimatorConfig, config_changes
from bubble_rt.estimation.plausibility import (
    ImageGuard,
    PlausibilitySettings,
    PressureGuard,
    ReferenceRefused,
    capture_time,
    estimate_problems,
    noisy_source,
    reference_force_problem,
    reference_pressure_problem,
)
from bubble_rt.estimation.registry import EstimatorKind, estimator_kind
from bubble_rt.estimation.types import Estimate
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh


def capture_settings(config: Any, *, realtime: bool, layout: str = "sim") -> dict[str, Any]:
    """``Pipeline.capture`` keyword arguments from a daemon configuration (``bubble_rt.config.
    DaemonConfig``, read through its ``estimator``, ``flow`` and ``solver`` sections): kind, mesh,
    fit, EstimatorConfig and FlowSettings. Every command that takes ``--config`` builds its
    pipeline from here. ``realtime`` applies ``solver.time_limit_ms`` (the daemon); offline
    callers solve every frame to tolerance, so their results do not depend on the machine.
    ``layout`` (the data's: "sim", "punyo", "rosbag", ...) picks the sensor profile when the
    configuration says ``profile = "auto"``; its ambient pressure applies unless the
    configuration gives one, and its bubble bounds the pressure rate of the plausibility
    checks (``[plausibility]``, ``pressure.min_pa``/``max_pa``)."""
    from bubble_rt.estimation.estimator import CONFIG_KEYS
    from bubble_rt.estimation.solver import SolverSettings

    ec, fc = config.estimator, config.flow
    limit = config.solver.time_limit_ms / 1e3 if realtime else 0.0
    est = EstimatorConfig(solver=SolverSettings(time_limit=limit))
    values = {key: getattr(ec, key) for key in CONFIG_KEYS}
    profile = ec.sensor_profile(layout)
    if not values["ambient_pa"]:
        values["ambient_pa"] = profile.ambient_pa
    return {
        "mesh": ec.mesh,
        "fit": ec.fit_mesh,
        "kind": ec.kind,
        "config": dataclasses.replace(est, **config_changes(est, values)),
        "flow": FlowSettings(
            method=fc.method,
            scale=fc.scale,
            forward_backward=fc.forward_backward,
            refine_window_px=fc.refine_window_px,
        ),
        "plausibility": PlausibilitySettings.from_config(config, profile.bubble),
    }


class Pipeline:
    """One sensor's estimation path.

    Args:
        mesh: the estimator mesh (fitted to the reference surface, mesh frame).
        camera: camera model (pose camera -> mesh frame).
        reference: the untouched state (``Reference.capture``).
        kind: registered estimator kind ("fem", "frictionless", ...).
        config: EstimatorConfig (default: the paper's values).
        flow: FlowSettings of the deformation tracker (tracked kinds only).
        plausibility: thresholds of the plausibility checks (None: no checks). With them,
            ``check_reference`` must be called with the reference frames before the first
            frame (``capture`` and ``retake_reference`` do).

    Attributes:
        kind: the EstimatorKind; ``params`` lists what ``reconfigure`` accepts.
        estimator: the estimator object.
        tracker: the deformation tracker (None when the kind reads frames itself).
    """

    def __init__(
        self,
        mesh: Mesh,
        camera: Camera,
        reference: Reference,
        *,
        kind: str = "fem",
        config: EstimatorConfig | None = None,
        flow: FlowSettings | None = None,
        plausibility: PlausibilitySettings | None = None,
    ) -> None:
        self.kind: EstimatorKind = estimator_kind(kind)
        self.mesh = mesh
        self.camera = camera
        self.config = config or EstimatorConfig()
        self.flow = flow or FlowSettings()
        self.tracker: Tracker | None = None
        self.reference = reference
        self.estimator: Any = self._build_estimator()
        self._build_tracker()
        self.plausibility = plausibility
        self._pressure: PressureGuard | None = None
        self._images: ImageGuard | None = None

    # ---------------------------------------------------------------- construction
    @classmethod
    def capture(
        cls,
        frames: Sequence[Frame] | Frame,
        camera: Camera,
        *,
        mesh: Mesh | str = "medium",
        fit: bool = True,
        kind: str = "fem",
        config: EstimatorConfig | None = None,
        flow: FlowSettings | None = None,
        plausibility: PlausibilitySettings | None = None,
    ) -> Pipeline:
        """Capture the reference from untouched ``frames``, take the mesh (a Mesh, or a preset
        name, node count or file: ``Mesh.from_spec``), fit it onto the reference surface when
        ``fit``, and build the pipeline. With ``plausibility``, a reference the checks refuse
        raises :class:`~bubble_rt.estimation.plausibility.ReferenceRefused` (what to check)."""
        frames = [frames] if isinstance(frames, Frame) else list(frames)
        reference = Reference.capture(frames)
        if plausibility is not None:  # before fitting a mesh to it
            problem = reference_pressure_problem(plausibility, reference.pressure_pa)
            if problem:
                raise ReferenceRefused(problem)
        fitted = fitted_mesh(mesh, reference, camera, fit=fit)
        pipe = cls(
            fitted,
            camera,
            reference,
            kind=kind,
            config=config,
            flow=flow,
            plausibility=plausibility,
        )
        pipe.check_reference(frames)
        return pipe

    def _build_estimator(self) -> Any:
        return self.kind.build(self.mesh, self.config, self.camera, self.reference)

    def _build_tracker(self) -> None:
        if self.kind.tracked:
            self.tracker = make_tracker(self.mesh, self.camera, self.reference, self.flow)

    # ---------------------------------------------------------------- plausibility
    #: Reference frames solved by ``check_reference`` (evenly spread): bounds the start cost.
    REFERENCE_FRAMES_CHECKED = 5

    def check_reference(self, frames: Sequence[Frame]) -> None:
        """With plausibility settings: refuse (:class:`ReferenceRefused`, saying what to
        check) a reference whose pressure is out of range or whose untouched ``frames`` do
        not read about zero force; then arm the per-frame checks. No-op without settings."""
        s = self.plausibility
        if s is None:
            return
        problem = reference_pressure_problem(s, self.reference.pressure_pa)
        if problem:
            raise ReferenceRefused(problem)
        frames = list(frames)
        k = min(len(frames), self.REFERENCE_FRAMES_CHECKED)
        picks = sorted({int(round(i)) for i in np.linspace(0, len(frames) - 1, k)})
        forces = []
        for i in picks:
            est = self._solve(frames[i], self._track(frames[i]))
            forces.append(float(np.linalg.norm(np.nan_to_num(est.net_force, nan=np.inf))))
        # The checks' solves leave no trace: the first real frame starts as if they never ran.
        if self.tracker is not None and hasattr(self.tracker, "reset_history"):
            self.tracker.reset_history()
        self.cold_start()
        problem = reference_force_problem(s, forces)
        if problem:
            raise ReferenceRefused(problem)
        self._pressure = PressureGuard(s, self.reference.pressure_pa, capture_time(frames[-1]))
        self._images = ImageGuard(s, frozen_check=noisy_source(frames))

    def retake_reference(self, frames: Sequence[Frame]) -> None:
        """Tare on untouched ``frames``: the new reference, checked (``check_reference``);
        a refused one raises ReferenceRefused and the previous reference stays."""
        before = (self.reference, self.estimator, self.tracker, self._pressure, self._images)
        self.set_reference(Reference.capture(frames))
        try:
            self.check_reference(frames)
        except ReferenceRefused:
            (self.reference, self.estimator, self.tracker, self._pressure, self._images) = before
            raise

    def _check_frame(self, frame: Frame) -> tuple[Frame, list[str]]:
        """The frame with an implausible pressure replaced by the last good one, and the
        degraded reasons of its inputs (none without plausibility settings)."""
        if self._pressure is None or self._images is None:
            return frame, []
        reasons = self._images.check(frame)
        p, why = self._pressure.check(capture_time(frame), frame.pressure_pa)
        if why:
            frame = dataclasses.replace(frame, pressure_pa=p)
        return frame, reasons + why

    # ---------------------------------------------------------------- per frame
    def deform(self, frame: Frame) -> Deformation | None:
        """Stage one: the frame's node displacements (None when the kind reads frames itself),
        carrying the degraded reasons of its inputs."""
        if self.tracker is None:
            return None
        frame, reasons = self._check_frame(frame)
        deformation = self._track(frame)
        assert deformation is not None
        deformation.degraded_reasons = reasons
        return deformation

    def solve(self, frame: Frame, deformation: Deformation | None) -> Estimate:
        """Stage two: forces and contact from stage one's ``deformation`` of ``frame``, with
        the degraded reasons of the frame's inputs and of the result."""
        if deformation is None:
            frame, reasons = self._check_frame(frame)
        else:
            reasons = list(deformation.degraded_reasons)
        est = self._solve(frame, deformation)
        if self.plausibility is not None:
            reasons += estimate_problems(
                self.plausibility, est.valid_node_fraction, est.net_force, est.contact
            )
        est.degraded_reasons = reasons
        return est

    def _track(self, frame: Frame) -> Deformation | None:
        return self.tracker.track(frame) if self.tracker is not None else None

    def _solve(self, frame: Frame, deformation: Deformation | None) -> Estimate:
        if deformation is None:
            est: Estimate = self.estimator.process(frame)
            est.pressure_delta_pa = self.reference.pressure_change(frame)
            return est
        est = self.estimator.estimate(deformation.U, deformation.dp)
        # The tracker's stages ("flow", "lift") before the estimator's, in one dict.
        return dataclasses.replace(
            est,
            timings_ms={**deformation.timings_ms, **est.timings_ms},
            valid_node_fraction=float(deformation.valid_fraction),
            pressure_delta_pa=float(deformation.dp),
        )

    def process(self, frame: Frame) -> Estimate:
        """Both stages on one frame."""
        return self.solve(frame, self.deform(frame))

    # ---------------------------------------------------------------- changes
    def cold_start(self) -> None:
        """The next solve starts as the first one did: no warm start, and the solver's
        frame-to-frame state (force scale, rho) reset."""
        solver = getattr(self.estimator, "solver", None)
        if solver is not None and hasattr(solver, "cold_start"):
            solver.cold_start()

    def set_reference(self, reference: Reference) -> None:
        """Measure against a new untouched state (tare); the mesh stays."""
        self.reference = reference
        # Every kind depends on the reference: the FEM model is linearised about its rest
        # pressure, the frictionless baseline reads its surface.
        self.estimator = self._build_estimator()
        self._build_tracker()

    def follow_reference(self, reference: Reference, offset: Any = None) -> bool:
        """Re-zero (the daemon, a few ms): from the next frame on, measure dp against
        ``reference.pressure_pa``, the flow against ``reference.rgb`` and the displacements
        from the mesh nodes moved by ``offset`` (N x 3, m; None: not moved). The mesh and the
        estimator (linearised about the last ``set_reference``) stay. False (nothing changed)
        for kinds that read frames themselves."""
        if not self.kind.tracked or self.tracker is None:
            return False
        self.tracker.set_reference(reference)
        self.tracker.set_offset(offset)
        return True

    @property
    def params(self) -> tuple[str, ...]:
        """The ``[estimator]`` keys ``reconfigure`` accepts for this kind."""
        return self.kind.params

    def reconfigure(self, values: Mapping[str, float]) -> None:
        """Change ``[estimator]`` parameters (k_f, k_u, youngs_modulus, k_const, k_linear) between
        frames. ValueError names a parameter this kind does not have; nothing changes then."""
        bad = [k for k in values if k not in self.kind.params]
        if bad:
            raise ValueError(
                f"the {self.kind.name!r} estimator has no parameter {', '.join(bad)} "
                f"(it has {', '.join(self.kind.params)})"
            )
        changes = config_changes(self.config, values)
        self.estimator.reconfigure(**changes)
        self.config = dataclasses.replace(self.config, **changes)


def fitted_mesh(
    mesh: Mesh | str, reference: Reference, camera: Camera, *, fit: bool = True
) -> Mesh:
    """The estimator mesh: ``mesh`` (a Mesh, or a preset name, node count or file:
    ``Mesh.from_spec``), lifted onto the reference surface the camera sees when ``fit``."""
    template = mesh if isinstance(mesh, Mesh) else Mesh.from_spec(mesh)
    if not fit:
        return template
    from bubble_rt.estimation.fitting import fit_mesh

    return fit_mesh(template, reference, camera)


__all__ = ["Pipeline", "fitted_mesh"]
