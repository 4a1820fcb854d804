"""Node displacements from RGBD frames (docs/deformation.md).

For every mesh node: project its reference position into the camera, sample the dense optical
flow (reference RGB -> current RGB) there, lift the displaced pixel to 3D through the current,
hole-filled depth map, and take ``U = x_cur - x_ref`` (N x 3, metres, mesh frame). Nodes the
camera cannot see, with missing depth or unreliable flow are flagged and their displacement is
filled from valid neighbours by a Laplacian solve over the mesh, so no NaN leaves this stage.

The heavy parts (flow, hole filling, lifting) run in C++ (``bubble_rt._core``) with the GIL
released. Trackers are made by flow-method name (:func:`make_tracker`): the image methods here,
and "oracle" (the simulator's ground-truth displacements, no images), which the simulator
registers (``bubble_rt.sim.oracle``) so that estimation never reads a frame's ground truth.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.estimation.lifting import (
    harmonic_fill,
    leave_one_out_residual,
    lifted_points,
    mesh_laplacian,
    neighbour_outliers,
    neighbour_table,
)
from bubble_rt.estimation.names import (
    DEFAULT_FLOW_METHOD,
    DEFAULT_REFINE_WINDOW_PX,
    FLOW_METHODS,
    IMAGE_FLOW_METHODS,
    refine_window_problem,
)
from bubble_rt.estimation.params import FLOW_SCALE
from bubble_rt.frames import Frame, FrameError
from bubble_rt.mesh import Mesh

_DIS_PRESETS = {"dis_ultrafast": 0, "dis_fast": 1, "dis_medium": 2}

#: The public implementation's Farneback parameters (method "farneback_heavy").
FARNEBACK_PUBLIC: dict[str, Any] = dict(
    pyr_scale=0.5, levels=30, winsize=50, iterations=5, poly_n=7, poly_sigma=1.5, gaussian=True
)

#: Reasons a node is flagged (bits of ``Deformation.flags``).
FLAG_OUTSIDE_IMAGE = 1
FLAG_INVALID_DEPTH = 2
FLAG_FLOW_UNRELIABLE = 4
FLAG_NON_FINITE = 8
FLAG_OUTLIER = 16
FLAG_DEPTH_JUMP = 32


@dataclass(frozen=True)
class FlowSettings:
    """How frames become node displacements.

    Attributes:
        method: "dis_ultrafast" | "dis_fast" | "dis_medium" (OpenCV DISOpticalFlow presets),
            "farneback" (the Farneback fields below), "farneback_heavy" (the public
            implementation's set, FARNEBACK_PUBLIC), or "oracle" (simulator ground truth, no
            images; the simulator provides that tracker).
        scale: images are resized by this factor (``params.FLOW_SCALE``) before the flow.
        margin_px: margin (pixels) around the box the mesh projects into; flow is computed
            only inside that region.
        forward_backward: also compute the backward flow and flag nodes whose round trip
            misses by more than ``fb_threshold_px``.
        fb_threshold_px: forward-backward tolerance, pixels.
        max_fill_level: depth filled from pyramid level k bridges holes about 2^k pixels across;
            nodes whose depth comes from a coarser level are flagged.
        depth_smoothing: Gauss-Seidel sweeps that make the hole fill harmonic.
        dis_finest_scale: finest pyramid level the DIS flow is computed at (0 = working
            resolution); None keeps each preset exactly as OpenCV defines it (2 for the
            ultrafast and fast presets, 1 for medium).
        dis_refinement_iterations: variational refinement iterations; None keeps the preset.
        dis_patch_stride: pixels between neighbouring DIS patches (1 to the patch size, 8);
            None keeps the preset's (4, or 3 for medium).
        refine_window_px: window (odd, pixels) of the Lucas-Kanade refinement of the flow at
            each node, started from the dense flow; 0: the dense flow as sampled. With it
            the DIS preset's own pyramid level 2 reads the calibration seeds as level 1 read
            them without it, in half the flow time (docs/evaluation.md, "Speed").
        pyr_scale, levels, winsize, iterations, poly_n, poly_sigma, gaussian: Farneback
            parameters for method "farneback" (defaults: OpenCV's documented example values
            0.5, 3, 15, 3, 5, 1.2, box window).
        clamp_rim: rim nodes are clamped (U = 0) whatever the images say; the edge of the
            membrane is where depth is least reliable and the solver holds the rim anyway.
        max_displacement_m: measured |U| above this flags the node (a depth edge, not the
            membrane).
        outlier_m: a node whose U differs by more than this from the median of its measured
            neighbours is flagged (isolated depth/flow glitches); None disables.
        outlier_relative: where the neighbours themselves moved, the tolerance is this
            fraction of their median displacement when that is larger than ``outlier_m``. A
            pin's tip stands 4-5 mm deeper than its neighbours at 12-19 mm (0.2-0.45 of
            theirs, the larger share on coarser meshes), and a flat 4 mm tolerance erased the
            tip of every firm pin press (docs/phantom-forces.md). The glitches ``outlier_m``
            is for stand 4-26 mm apart from neighbours that moved 1.5 mm at most.
        jump_m: depth-jump tolerance along the camera ray, metres. A measured node is flagged
            (FLAG_DEPTH_JUMP) when its displacement along its camera ray differs by more than
            this both from the membrane around it (the harmonic interpolant of every other
            measured node, rim clamped: :func:`leave_one_out_residual`) and from its own
            displacement in the tracker's previous frame (0 after a new reference). It catches
            what ``outlier_m`` cannot: a node whose neighbours are all unmeasured (near the rim
            of a real Punyo's depth). Default 8 mm: on simulated presses a node stands out from
            its surroundings by at most 5.0 mm (point indenter, medium mesh), the real depth
            jumps are 18-19 mm (docs/phantom-forces.md). None disables; trackers without
            depth images (the simulator's oracle) have no such check.
    """

    method: str = DEFAULT_FLOW_METHOD
    scale: float = 1.0
    margin_px: int = 24
    forward_backward: bool = False
    fb_threshold_px: float = 1.0
    max_fill_level: int = 3
    depth_smoothing: int = 4
    dis_finest_scale: int | None = None
    dis_refinement_iterations: int | None = None
    dis_patch_stride: int | None = None
    refine_window_px: int = DEFAULT_REFINE_WINDOW_PX
    pyr_scale: float = 0.5
    levels: int = 3
    winsize: int = 15
    iterations: int = 3
    poly_n: int = 5
    poly_sigma: float = 1.2
    gaussian: bool = False
    clamp_rim: bool = True
    max_displacement_m: float = 0.03
    outlier_m: float | None = 0.004
    outlier_relative: float = 0.5
    jump_m: float | None = 0.008

    def __post_init__(self) -> None:
        if self.method not in FLOW_METHODS:
            raise ValueError(f"flow method {self.method!r} unknown; choose one of {FLOW_METHODS}")
        problem = FLOW_SCALE.problem(self.scale)
        if problem is not None:
            raise ValueError(f"flow scale {problem}")
        if self.margin_px < 0:
            raise ValueError(f"margin_px must be >= 0, got {self.margin_px}")
        problem = refine_window_problem(self.refine_window_px)
        if problem is not None:
            raise ValueError(f"refine_window_px {problem}")
        if self.jump_m is not None and not self.jump_m > 0:
            raise ValueError(f"jump_m must be > 0 (or None), got {self.jump_m}")

    def farneback_params(self) -> dict[str, Any]:
        """Farneback parameters in effect (the heavy set for method "farneback_heavy")."""
        if self.method == "farneback_heavy":
            return dict(FARNEBACK_PUBLIC)
        return dict(
            pyr_scale=self.pyr_scale,
            levels=self.levels,
            winsize=self.winsize,
            iterations=self.iterations,
            poly_n=self.poly_n,
            poly_sigma=self.poly_sigma,
            gaussian=self.gaussian,
        )


@dataclass
class Reference:
    """The untouched sensor state that displacements and dp are measured against.

    Attributes:
        rgb: H x W x 3 uint8, per-pixel mean of the captured frames (the flow reference), or
            None for image-less (oracle) frames.
        depth: H x W float32 metres, per-pixel mean over the frames where the pixel is valid
            (0 where it never is), or None.
        pressure_pa: mean pressure, pascals.
        t: time of the last captured frame, seconds.
        n_frames: number of frames averaged.
    """

    rgb: NDArray[np.uint8] | None
    depth: NDArray[np.float32] | None
    pressure_pa: float
    t: float = 0.0
    n_frames: int = 1

    @classmethod
    def capture(cls, frames: Sequence[Frame] | Frame) -> Reference:
        """Average one or more untouched frames (images must all have the same size)."""
        if isinstance(frames, Frame):
            frames = [frames]
        frames = list(frames)
        if not frames:
            raise ValueError("Reference.capture needs at least one frame")
        shapes = {f.shape for f in frames}
        if len(shapes) > 1:
            raise FrameError(f"reference frames differ in size: {sorted(map(str, shapes))}")
        rgb = None
        if all(f.rgb is not None for f in frames):
            acc = np.zeros(frames[0].rgb.shape, np.float64)  # type: ignore[union-attr]
            for f in frames:
                acc += f.rgb
            rgb = np.clip(np.rint(acc / len(frames)), 0, 255).astype(np.uint8)
        depth = None
        if all(f.depth is not None for f in frames):
            s = np.zeros(frames[0].depth.shape, np.float64)  # type: ignore[union-attr]
            n = np.zeros(s.shape, np.int32)
            for f in frames:
                d = np.asarray(f.depth)
                ok = np.isfinite(d) & (d > 0)
                s[ok] += d[ok]
                n += ok
            depth = np.where(n > 0, s / np.maximum(n, 1), 0.0).astype(np.float32)
        pressure = float(np.mean([f.pressure_pa for f in frames]))
        return cls(rgb=rgb, depth=depth, pressure_pa=pressure, t=frames[-1].t, n_frames=len(frames))

    def pressure_change(self, frame: Frame) -> float:
        """dp: the frame's pressure minus this reference's, pascals (the one place it is
        computed: trackers, and the pipeline for kinds that read frames themselves)."""
        return float(frame.pressure_pa) - float(self.pressure_pa)


@dataclass
class Deformation:
    """Node displacements of one frame.

    Attributes:
        U: N x 3 displacements x_cur - x_ref, metres, mesh frame (never NaN).
        valid: N bool, True where U was measured (False: filled from neighbours).
        valid_fraction: mean of ``valid``.
        dp: pressure now minus reference pressure, pascals.
        timings_ms: {"flow": ms, "lift": ms, "fill": ms} (``DeformationTracker.track``).
        flags: N uint8 reason bits (FLAG_*), 0 for valid nodes.
        flow: N x 2 flow sampled at the node projections (pixels), zeros for oracle.
        degraded_reasons: why the frame's input is implausible (set by the Pipeline's checks).
    """

    U: NDArray[np.float64]
    valid: NDArray[np.bool_]
    valid_fraction: float
    dp: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    flags: NDArray[np.uint8] | None = None
    flow: NDArray[np.float64] | None = None
    degraded_reasons: list[str] = field(default_factory=list)


def _roi(uv: NDArray, ok: NDArray, camera: Camera, margin: int) -> tuple[int, int, int, int]:
    if not ok.any():
        return 0, 0, camera.width, camera.height
    lo = np.floor(uv[ok].min(axis=0)).astype(int) - margin
    hi = np.ceil(uv[ok].max(axis=0)).astype(int) + margin + 1
    x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    x1, y1 = min(int(hi[0]), camera.width), min(int(hi[1]), camera.height)
    return x0, y0, max(x1 - x0, 8), max(y1 - y0, 8)


class Tracker(Protocol):
    """What the pipeline needs from a deformation tracker."""

    def track(self, frame: Frame) -> Deformation: ...

    def set_reference(self, reference: Reference) -> None: ...

    def set_offset(self, offset: NDArray[np.float64] | None) -> None: ...


#: (mesh, camera, reference, settings) -> Tracker
TrackerFactory = Callable[[Mesh, Camera, Reference, FlowSettings], Tracker]
_TRACKERS: dict[str, TrackerFactory] = {}


def register_tracker(method: str, factory: TrackerFactory) -> None:
    """Make flow method ``method`` (one of FLOW_METHODS) build its tracker with ``factory``."""
    if method not in FLOW_METHODS:
        raise ValueError(f"flow method {method!r} unknown; choose one of {FLOW_METHODS}")
    _TRACKERS[method] = factory


def make_tracker(
    mesh: Mesh, camera: Camera, reference: Reference, settings: FlowSettings | None = None
) -> Tracker:
    """The deformation tracker of ``settings.method`` (image methods: DeformationTracker)."""
    settings = settings or FlowSettings()
    factory = _TRACKERS.get(settings.method)
    if factory is None:
        raise ValueError(
            f"flow method {settings.method!r} has no tracker here: the simulator provides it "
            "(import bubble_rt.sim first)"
        )
    return factory(mesh, camera, reference, settings)


class NodeTracker:
    """What every tracker shares: the mesh, the reference, and turning raw per-node
    displacements and flags into a :class:`Deformation` (outlier and depth-jump flags, rim
    clamp, harmonic fill of the flagged nodes).

    Attributes:
        rays: N x 3 unit camera rays through the reference nodes (mesh frame), the direction a
            depth jump moves a lifted node along; None (no depth images, e.g. the simulator's
            oracle): no depth-jump check.
    """

    def __init__(self, mesh: Mesh, reference: Reference, settings: FlowSettings) -> None:
        self.mesh = mesh
        self.reference = reference
        self.settings = settings
        self.x_ref = np.array(mesh.vertices, dtype=np.float64)
        self._laplacian = mesh_laplacian(mesh)
        self._rim = np.zeros(mesh.n_nodes, bool)
        self._rim[mesh.boundary] = True
        self._neighbours = neighbour_table(self._laplacian)
        self.rays: NDArray[np.float64] | None = None
        self._previous = np.zeros_like(self.x_ref)

    def set_reference(self, reference: Reference) -> None:
        """Measure against a new reference from now on (tare)."""
        self.reference = reference
        self.reset_history()

    def set_offset(self, offset: NDArray[np.float64] | None) -> None:
        """Measure displacements from the reference nodes moved by ``offset`` (N x 3, m; None:
        from the mesh itself): the daemon's re-zeroing follows the untouched membrane's slow
        drift (a warmer gas bulges it) without refitting the mesh."""
        base = np.array(self.mesh.vertices, dtype=np.float64)
        if offset is not None:
            off = np.asarray(offset, dtype=np.float64)
            if off.shape == base.shape and np.isfinite(off).all():
                base = base + off
        self.x_ref = base
        self.reset_history()

    def reset_history(self) -> None:
        """Forget the previous frames: the depth-jump check compares the next frame with the
        reference (U = 0). Called by ``set_reference``."""
        self._previous = np.zeros_like(self.x_ref)

    @staticmethod
    def _along_ray(
        rays: NDArray[np.float64], V: NDArray[np.float64], nodes: NDArray[np.intp]
    ) -> NDArray[np.float64]:
        """|displacements ``V``| (len(nodes) x 3) of ``nodes`` along their ``rays`` (metres)."""
        return np.abs(np.einsum("ij,ij->i", V, rays[nodes]))

    def _depth_jumps(
        self,
        rays: NDArray[np.float64],
        U: NDArray[np.float64],
        known: NDArray[np.bool_],
        tol: float,
    ) -> NDArray[np.intp]:
        """Measured nodes (``known`` minus the rim) whose displacement along the ray moved by
        more than ``tol`` (m) since the previous frame and stands out by more than ``tol`` from
        the membrane around it (``U``: N x 3, rim rows already 0 when clamped). The history
        test runs first: it is a subtraction, the neighbour test a small solve."""
        cand = np.flatnonzero(known & ~self._rim)
        moved = self._along_ray(rays, U[cand] - self._previous[cand], cand) > tol
        cand = cand[moved]
        if len(cand) == 0:
            return cand
        r = leave_one_out_residual(self._laplacian, U, known, cand)
        return cand[self._along_ray(rays, r, cand) > tol]

    def dp(self, frame: Frame) -> float:
        """Pressure change of ``frame`` against the reference, Pa."""
        return self.reference.pressure_change(frame)

    def finish(
        self, U: NDArray, flags: NDArray, dp: float, timings: dict[str, float], flow: NDArray
    ) -> Deformation:
        """The Deformation from raw displacements ``U`` (N x 3, may hold NaN) and FLAG_* bits."""
        s = self.settings
        flags = flags.astype(np.uint8)
        flags[~np.isfinite(U).all(axis=1)] |= FLAG_NON_FINITE
        U = np.where(np.isfinite(U), U, 0.0)
        with np.errstate(invalid="ignore"):
            flags[np.linalg.norm(U, axis=1) > s.max_displacement_m] |= FLAG_OUTLIER
        if s.outlier_m is not None:
            out = neighbour_outliers(
                U, flags == 0, self._neighbours, s.outlier_m, s.outlier_relative
            )
            flags[out] |= FLAG_OUTLIER
        known = flags == 0
        Uk = U.copy()
        if s.clamp_rim:
            Uk[self._rim] = 0.0
            known |= self._rim
        if s.jump_m is not None and self.rays is not None:
            jumps = self._depth_jumps(self.rays, Uk, known, s.jump_m)
            flags[jumps] |= FLAG_DEPTH_JUMP
            known[jumps] = False
        valid = flags == 0
        U = harmonic_fill(self._laplacian, Uk, known)
        self._previous = U.copy()
        return Deformation(
            U=U,
            valid=valid,
            valid_fraction=float(valid.mean()),
            dp=dp,
            timings_ms=timings,
            flags=flags,
            flow=flow,
        )


class DeformationTracker(NodeTracker):
    """Turns frames into node displacements against a fixed reference (optical flow + lifting).

    Args:
        mesh: the reference mesh (mesh frame; nodes on the reference surface).
        camera: camera model; ``camera.pose`` maps camera to mesh coordinates.
        reference: captured untouched state (its RGB is the flow reference).
        settings: FlowSettings (an image method; "oracle" is the simulator's tracker).
    """

    def __init__(
        self,
        mesh: Mesh,
        camera: Camera,
        reference: Reference,
        settings: FlowSettings | None = None,
    ) -> None:
        settings = settings or FlowSettings()
        if settings.method not in IMAGE_FLOW_METHODS:
            raise ValueError(
                f"DeformationTracker runs the image methods {IMAGE_FLOW_METHODS}, not "
                f"{settings.method!r} (use make_tracker)"
            )
        super().__init__(mesh, reference, settings)
        self.camera = camera
        uv, z = camera.project(mesh.vertices)
        self.uv_ref = np.ascontiguousarray(uv, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            inside = (
                np.isfinite(uv).all(axis=1)
                & (z > 0)
                & (uv[:, 0] >= -0.5)
                & (uv[:, 1] >= -0.5)
                & (uv[:, 0] <= camera.width - 0.5)
                & (uv[:, 1] <= camera.height - 0.5)
            )
        self.visible = inside
        ray = self.x_ref - camera.pose_matrix[:3, 3]
        self.rays = ray / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)[:, None]
        self._pixel_tracker: Any = None
        self.roi = _roi(self.uv_ref, inside, camera, self.settings.margin_px)
        self.set_reference(reference)

    def set_reference(self, reference: Reference) -> None:
        """Measure against a new reference from now on (tare); mesh and camera stay."""
        from bubble_rt import _core

        camera, s = self.camera, self.settings
        if reference.rgb is None or reference.depth is None:
            raise FrameError("reference has no rgb/depth: image methods need an RGBD reference")
        Frame(reference.rgb, None, reference.pressure_pa).validate(camera)
        if reference.depth.shape != (camera.height, camera.width):
            raise FrameError(
                f"reference depth size {reference.depth.shape[1]} x {reference.depth.shape[0]} "
                f"differs from the camera's {camera.width} x {camera.height}"
            )
        if self._pixel_tracker is None:
            self._pixel_tracker = _core._PixelTracker(
                method=1 if s.method in _DIS_PRESETS else 0,
                dis_preset=_DIS_PRESETS.get(s.method, 2),
                scale=s.scale,
                forward_backward=s.forward_backward,
                dis_finest_scale=-1 if s.dis_finest_scale is None else s.dis_finest_scale,
                dis_refinement_iterations=(
                    -1 if s.dis_refinement_iterations is None else s.dis_refinement_iterations
                ),
                dis_patch_stride=-1 if s.dis_patch_stride is None else s.dis_patch_stride,
                refine_window=s.refine_window_px,
                **s.farneback_params(),
            )
        self._pixel_tracker.set_reference(np.ascontiguousarray(reference.rgb), *self.roi)
        self.reference = reference
        self.reset_history()

    # ------------------------------------------------------------------ per frame
    def track(self, frame: Frame) -> Deformation:
        """Displacements of the mesh nodes in ``frame`` against the reference.

        One call into C++ (GIL released) computes the flow, fills the depth holes on a thread
        of its own meanwhile, samples the flow at the nodes and lifts them. Timings (ms):
        "flow" (flow + sampling), "lift" (the rest of the stage: the end of the fill, the
        lift, the checks and the fill of flagged nodes; flow + lift is the stage's wall time)
        and "fill" (the depth fill's own wall time, beside the flow)."""
        dp = self.dp(frame)
        frame.validate(self.camera, need_images=True)
        cam, s = self.camera, self.settings
        t0 = time.perf_counter()
        flow, flags, pinhole, lift_flags, filled, ms = self._pixel_tracker.track(
            np.ascontiguousarray(frame.rgb),
            frame.depth,
            self.uv_ref,
            s.fb_threshold_px,
            s.depth_smoothing,
            s.max_fill_level,
            cam.fx,
            cam.fy,
            cam.cx,
            cam.cy,
            cam.has_distortion,
        )
        flags[~self.visible] |= FLAG_OUTSIDE_IMAGE
        flags |= lift_flags
        x_cur = lifted_points(pinhole, lift_flags, filled, self.uv_ref + flow, cam)
        out = self.finish(x_cur - self.x_ref, flags, dp, {}, flow)
        total = (time.perf_counter() - t0) * 1e3
        out.timings_ms = {"flow": ms["flow"], "lift": total - ms["flow"], "fill": ms["fill"]}
        return out


for _method in IMAGE_FLOW_METHODS:
    register_tracker(_method, DeformationTracker)
