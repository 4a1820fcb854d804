"""A press's physics read from depth frames alone: the dent, its volume, pressure rise and force.

The same measurement reads a real recording and a simulated scene, so the simulator's physics
can be compared with a real sensor's on equal terms (docs/sim-punyo.md):

* the **dent** is the change of range along each camera ray between the untouched reference
  (per-pixel median of the reference frames) and a frame: ``dr = (z_ref - z) / cos(theta)``,
  positive where the membrane moved towards the camera. It is median-filtered (5 x 5 px) and
  restricted to the connected region of ``dr > DENT_FLOOR_M`` that sweeps the largest volume,
  so depth jumps elsewhere in the image (a real D405's mixed pixels) do not count, nor do
  reference pixels whose frames disagree;
* its **depth** is the largest filtered ``dr`` (m), its **area** above 2 mm is the surface area
  (m^2) of the pixels deeper than that, and its **volume** (m^3) is the volume swept between the
  two surfaces along the rays, exact for a pinhole camera: a pixel's solid angle times
  ``(r_ref^3 - r^3) / 3`` is ``(z_ref^3 - z^3) / (3 fx fy)``; the area counts each pixel's
  footprint ``(z / fx)(z / fy)`` normal to the optical axis;
* the **pressure rise** (Pa) and the **force** (N, the magnitude of the wrench minus the
  reference frames' mean, or the simulator's true net force) come with the frame.

The measurement borrows nothing from the estimator: it reads depth images, pressures and
wrenches only. The identification (:func:`identify`) also fits the estimator's mesh to the real
reference for the rest dome, and :func:`estimator_on_press` reads a simulated press with the
estimator.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from bubble_rt.camera import Camera

#: Depth change (m) that bounds the dent's region.
DENT_FLOOR_M = 0.5e-3
#: The depth (m) above which the dent's area is reported (issue 18: "more than 2 mm deep").
AREA_DEPTH_M = 2.0e-3
#: Reference pixels whose frames spread by more than this (m) are not trusted.
REFERENCE_SPREAD_M = 1.0e-3
#: Depth changes beyond this (m) are depth jumps, not membrane motion.
JUMP_M = 0.015


@dataclass(frozen=True)
class DentReading:
    """One frame's dent: depth_m (largest change of range along the rays, m), area_m2 (surface
    deeper than ``AREA_DEPTH_M``), volume_m3 (swept between reference and frame along the rays),
    centre_px (u, v) of the deepest point (None without a dent), centre_m the depth-weighted
    centre of the part deeper than ``AREA_DEPTH_M`` on the reference surface (mesh frame, m;
    None when no part is), dp_pa (pressure rise), force_n (|f|)."""

    depth_m: float
    area_m2: float
    volume_m3: float
    centre_px: tuple[float, float] | None
    centre_m: tuple[float, float, float] | None
    dp_pa: float
    force_n: float


def reference_depth(depths: Sequence[NDArray]) -> NDArray[np.float64]:
    """Per-pixel median of the valid reference depths (H x W, m); NaN where fewer than half
    the frames read the pixel or where they spread by more than ``REFERENCE_SPREAD_M`` (mixed
    pixels at grazing angles, whose depth jumps between frames)."""
    D = np.stack([np.asarray(d, dtype=np.float64) for d in depths])
    ok = D > 0
    out = np.full(D.shape[1:], np.nan)
    enough = ok.sum(axis=0) * 2 >= len(D)
    Dv = np.where(ok, D, np.nan)[:, enough]
    with np.errstate(all="ignore"):
        med = np.nanmedian(Dv, axis=0)
        spread = np.nanmax(Dv, axis=0) - np.nanmin(Dv, axis=0)
    out[enough] = np.where(spread <= REFERENCE_SPREAD_M, med, np.nan)
    return out


def measure_dent(
    ref: NDArray[np.float64],
    depth: NDArray,
    camera: Camera,
    dp_pa: float = 0.0,
    force_n: float = 0.0,
) -> DentReading:
    """The dent of one frame's depth (H x W, m, 0 invalid) against the reference ``ref`` (from
    :func:`reference_depth`) seen by ``camera`` (its intrinsics; the pose is not used)."""
    z = np.where(np.asarray(depth, dtype=np.float64) > 0, depth, np.nan)
    h, w = ref.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    sec = np.sqrt(1 + ((u - camera.cx) / camera.fx) ** 2 + ((v - camera.cy) / camera.fy) ** 2)
    dr = (ref - z) * sec
    ok = np.isfinite(dr) & (np.abs(dr) < JUMP_M)
    med = ndimage.median_filter(np.where(ok, dr, 0.0), 5)
    if not ok.any() or med[ok].max() <= DENT_FLOOR_M:
        return DentReading(0.0, 0.0, 0.0, None, None, dp_pa, force_n)
    # Each pixel's swept volume; the dent is the connected region that sweeps the most (a
    # patch of depth jumps may be deeper, but it is small).
    swept = np.where(ok, ref**3 - z**3, 0.0) / (3.0 * camera.fx * camera.fy)
    lab, n = ndimage.label((med > DENT_FLOOR_M) & ok)
    per_region = ndimage.sum(swept, lab, index=np.arange(1, n + 1))
    region = lab == 1 + int(np.argmax(per_region))
    volume = float(swept[region].sum())
    iv, iu = np.unravel_index(int(np.argmax(np.where(region, med, -np.inf))), med.shape)
    # Each pixel counts its footprint (z / fx)(z / fy) in the plane normal to the optical axis
    # at its reference depth: the area as the camera sees it, not along the tilted surface.
    deep = region & (med > AREA_DEPTH_M)
    area = float(np.sum((ref[deep] / camera.fx) * (ref[deep] / camera.fy)))
    centre: tuple[float, float, float] | None = None
    if deep.any():
        pts = camera.depth_to_points(np.where(deep, ref, 0.0).astype(np.float32))
        wts = med[deep]
        c = (pts.reshape(h, w, 3)[deep] * wts[:, None]).sum(axis=0) / wts.sum()
        centre = (float(c[0]), float(c[1]), float(c[2]))
    return DentReading(
        depth_m=float(med[iv, iu]),
        area_m2=area,
        volume_m3=volume,
        centre_px=(float(iu), float(iv)),
        centre_m=centre,
        dp_pa=float(dp_pa),
        force_n=float(force_n),
    )


def press_readings(
    reference_frames: Sequence, frames: Sequence, camera: Camera, forces: Sequence[float]
) -> list[DentReading]:
    """The dent of every frame (``bubble_rt.frames.Frame`` with depth and pressure_pa) against
    the reference frames, each with its force magnitude (N) from ``forces``."""
    ref = reference_depth([f.depth for f in reference_frames])
    p0 = float(np.mean([f.pressure_pa for f in reference_frames]))
    return [
        measure_dent(ref, f.depth, camera, float(f.pressure_pa) - p0, float(fn))
        for f, fn in zip(frames, forces, strict=True)
    ]


def real_press(path: str, reference: Sequence[int] = (0, 1, 2, 3, 4)) -> list[DentReading]:
    """Every frame of a recording with wrenches (``open_recording``), read against the frames
    ``reference``; the force is |f - mean f over the reference| (N)."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(path)
    frames = [rec[i] for i in range(len(rec))]
    bias = np.mean([np.asarray(frames[i].wrench)[:3] for i in reference], axis=0)
    forces = [float(np.linalg.norm(np.asarray(f.wrench)[:3] - bias)) for f in frames]
    return press_readings([frames[i] for i in reference], frames, rec.camera, forces)


def sim_press(scene: object) -> list[DentReading]:
    """Every frame of a simulated scene (a Scene, name or path; name no image effects for an
    exact depth), read against 5 untouched frames; the force is the true net force (N)."""
    from bubble_rt.sim.simulator import Simulator

    sim = Simulator(scene)  # type: ignore[arg-type]
    frames = list(sim.frames())
    forces = [float(np.linalg.norm(f.truth.net_force)) for f in frames]  # type: ignore[union-attr]
    return press_readings(sim.reference_frames(5), frames, sim.camera, forces)


# ------------------------------------------------------------------ identification
#: Frames of a real press whose force is at least this (N) form its hold.
HOLD_FORCE_N = 4.5


@dataclass(frozen=True)
class PressSummary:
    """A press's hold, or the simulator at the real hold's dent: dent depth (m), area deeper
    than 2 mm (m^2), volume (m^3), pressure rise (Pa), force (N); centre_m (mesh frame, m; None
    when the dent has no part deeper than 2 mm)."""

    depth_m: float
    area_m2: float
    volume_m3: float
    dp_pa: float
    force_n: float
    centre_m: tuple[float, float, float] | None


def hold_summary(readings: Sequence[DentReading], force_n: float = HOLD_FORCE_N) -> PressSummary:
    """The mean over the frames whose force is at least ``force_n`` (the real press's hold)."""
    hold = [r for r in readings if r.force_n >= force_n and r.centre_m is not None]
    if not hold:
        raise ValueError(f"no frame with a dent deeper than 2 mm and {force_n} N or more")
    mean = lambda k: float(np.mean([getattr(r, k) for r in hold]))  # noqa: E731
    c = np.mean([r.centre_m for r in hold if r.centre_m is not None], axis=0)
    return PressSummary(
        mean("depth_m"),
        mean("area_m2"),
        mean("volume_m3"),
        mean("dp_pa"),
        mean("force_n"),
        (float(c[0]), float(c[1]), float(c[2])),
    )


def at_dent(readings: Sequence[DentReading], depth_m: float) -> PressSummary:
    """A simulated ramp press interpolated to the dent depth ``depth_m`` (readings in order of
    increasing depth; the last frame's centre; frames before the dent shows are left out)."""
    readings = [r for r in readings if r.depth_m > 0]
    d = np.array([r.depth_m for r in readings])
    if not np.all(np.diff(d) > 0) or not d[0] <= depth_m <= d[-1]:
        raise ValueError(
            f"the press's dents {np.round(d * 1e3, 2)} mm do not bracket "
            f"{depth_m * 1e3:.2f} mm monotonically"
        )
    f = lambda k: float(np.interp(depth_m, d, [getattr(r, k) for r in readings]))  # noqa: E731
    return PressSummary(
        depth_m, f("area_m2"), f("volume_m3"), f("dp_pa"), f("force_n"), readings[-1].centre_m
    )


def dp_at_force(readings: Sequence[DentReading], force_n: float) -> float:
    """The pressure rise (Pa) of a simulated ramp press interpolated to the force ``force_n``
    (frames before the dent shows are left out)."""
    readings = [r for r in readings if r.depth_m > 0]
    f = np.array([r.force_n for r in readings])
    if not np.all(np.diff(f) > 0) or not f[0] <= force_n <= f[-1]:
        raise ValueError(f"the press's forces {np.round(f, 2)} N do not bracket {force_n:.2f} N")
    return float(np.interp(force_n, f, [r.dp_pa for r in readings]))


def press_scene(
    physics: object,
    at: tuple[float, float],
    radius_m: float,
    depth_m: float,
    profile: str = "punyo",
    frames: int = 9,
) -> object:
    """A ramp press of a sphere of radius ``radius_m`` along the surface normal above the
    footprint point ``at`` (mesh frame, m), from 1 mm short of touching to ``depth_m`` past
    first touch in ``frames`` frames, on ``physics`` (a ``PhysicsSpec``) with the sensor
    (camera) of ``profile``; gas compression on, no friction, no image effects."""
    from dataclasses import asdict

    from bubble_rt.sim.scene import scene_from_dict

    ph = {k: v for k, v in asdict(physics).items() if v is not None}  # type: ignore[call-overload]
    t_end = (frames - 1) / 30.0
    return scene_from_dict(
        {
            "name": "press",
            "profile": profile,
            "frames": frames,
            "physics": ph,
            "indenter": {"shapes": [{"type": "sphere", "radius": radius_m}]},
            "trajectory": {
                "keyframes": [
                    {"t": 0.0, "at": list(at), "depth": -1.0e-3},
                    {"t": t_end, "at": list(at), "depth": depth_m},
                ]
            },
            "effects": {"gas_compression": True},
        }
    )


def real_rest_apex(path: str, reference: Sequence[int] = (0, 1, 2, 3, 4)) -> float:
    """Apex height (m) above the rim of the medium mesh fitted to a recording's untouched
    frames (``bubble_rt.estimation.fitting.fit_mesh``)."""
    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.estimation.fitting import fit_mesh
    from bubble_rt.io.recordings import open_recording
    from bubble_rt.mesh import Mesh

    rec = open_recording(path)
    ref = Reference.capture([rec[i] for i in reference])
    return float(fit_mesh(Mesh.preset("medium"), ref, rec.camera).vertices[:, 2].max())


def dome_gap(path: str, scene: object, reference: Sequence[int] = (0, 1, 2, 3, 4)) -> Any:
    """Height differences (m) of the medium mesh fitted to a recording's untouched frames
    against a simulated scene's inflated dome at the same footprint points (mesh frames, rim
    z = 0): an array over the fitted mesh's interior nodes, simulated minus real."""
    from scipy.interpolate import LinearNDInterpolator

    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.estimation.fitting import fit_mesh
    from bubble_rt.io.recordings import open_recording
    from bubble_rt.mesh import Mesh
    from bubble_rt.sim.simulator import Simulator

    rec = open_recording(path)
    fitted = fit_mesh(
        Mesh.preset("medium"), Reference.capture([rec[i] for i in reference]), rec.camera
    )
    ref_v = Simulator(scene).run.ref_vertices  # type: ignore[arg-type]
    height = LinearNDInterpolator(ref_v[:, :2], ref_v[:, 2])
    v = fitted.vertices[fitted.interior]
    return np.asarray(height(v[:, :2]) - v[:, 2])


def inflated_apex(physics: object, sim_nodes: int = 2000) -> float:
    """Apex height (m) of the simulator's bubble inflated with ``physics`` (a PhysicsSpec)."""
    from bubble_rt.sim import physics as sp

    ph: Any = physics
    mesh = sp.default_rest_mesh(sim_nodes, rest_dome_height_m=ph.rest_dome_height_m)
    sim = sp.MembraneSim(
        mesh,
        sp.MembraneMaterial(E=ph.youngs_modulus_pa, thickness=ph.thickness_m),
        sp.GasSettings(
            gauge_pressure_pa=ph.gauge_pressure_pa,
            atmospheric_pa=ph.atmospheric_pa,
            chamber_volume_m3=ph.chamber_volume_m3,
        ),
    )
    return float(sim.inflate().vertices[:, 2].max())


def _secant(fn: Any, x0: float, x1: float, target: float, tol: float, n: int = 8) -> float:
    """x with fn(x) = target by the secant method from x0, x1 (fn increasing)."""
    f0, f1 = fn(x0) - target, fn(x1) - target
    for _ in range(n):
        if abs(f1) <= tol or f1 == f0:
            break
        x0, x1, f0 = x1, x1 - f1 * (x1 - x0) / (f1 - f0), f1
        f1 = fn(x1) - target
    return x1


@dataclass(frozen=True)
class Identified:
    """A real press's physics: the real hold, the simulator's press with the identified
    physics at the same dent, the identified ``PhysicsSpec`` and the sphere's radius (m)."""

    real: PressSummary
    real_apex_m: float
    sim: PressSummary
    sim_dp_at_real_force_pa: float
    sim_apex_m: float
    physics: Any
    radius_m: float


def identify(
    path: str,
    fit: str = "gauge",
    ambient_pa: float | None = None,
    radius_m: float | None = None,
    log: Any = print,
) -> Identified:
    """Identify a real press's physics (docs/sim-punyo.md).

    1. The real hold (``hold_summary``): dent depth, area, volume, pressure rise, force; the
       real rest apex (``real_rest_apex``) and rest pressure (reference frames' mean).
    2. The bubble starts as the ``sim`` profile's (``PhysicsSpec.of``). ``fit = "gauge"``
       fits the rest gauge pressure with the membrane's modulus in proportion (a neo-Hookean
       membrane's inflated shape depends on p / (E t) only, so the sim's dome keeps its shape
       and every force scales with the pressure; with E held, no stress-free dome inflates to
       the real apex above about 10 kPa); the ambient becomes the rest reading minus the
       gauge pressure, so the simulated sensor reads the real absolute pressure.
       ``fit = "E"`` fits the modulus alone, with the gauge pressure the rest reading minus
       ``ambient_pa`` (default ``bubble_rt.sensor.PUNYO_BAROMETRIC_AMBIENT_PA``).
    3. The matched indenter: unless ``radius_m`` is given, the sphere whose dent, on the
       starting bubble, covers the real dent's area (deeper than 2 mm) at the real depth
       (secant on log radius, rounded to 0.1 mm; the dent's volume is reported against the
       real one's). Then for each trial value, the stress-free dome whose inflation gives the real rest apex
       (secant on ``inflated_apex``); then a sphere of ``radius_m`` pressed along the normal at
       the real dent's centre (``press_scene``) gives the force at the real dent depth; the
       secant method on log force finds the value that gives the real force.
    4. The chamber volume from the isothermal gas: the simulator's pressure rise for its dent
       volume sets an effective total volume ``P dV / dp``; the chamber volume is shifted by
       what the real press's ``P dV / dp`` asks for, and step 3 runs again (twice in all).
    Nothing is set by hand but, for ``fit = "E"``, the ambient pressure.
    """
    from dataclasses import replace

    from bubble_rt.io.recordings import open_recording
    from bubble_rt.sensor import PROFILES, PUNYO_BAROMETRIC_AMBIENT_PA
    from bubble_rt.sim.scene import PhysicsSpec

    if fit not in ("gauge", "E"):
        raise ValueError(f"fit must be 'gauge' or 'E', got {fit!r}")
    real = hold_summary(real_press(path))
    apex = real_rest_apex(path)
    rec = open_recording(path)
    p_rest = float(np.mean([rec[i].pressure_pa for i in range(5)]))
    log(
        f"real hold: dent {real.depth_m * 1e3:.2f} mm, area>2mm {real.area_m2 * 1e4:.2f} cm2, "
        f"volume {real.volume_m3 * 1e6:.2f} cm3, dp {real.dp_pa:.0f} Pa, |f| {real.force_n:.2f} N"
        f"; rest apex {apex * 1e3:.2f} mm, rest pressure {p_rest:.0f} Pa"
    )
    sim = PROFILES["sim"].bubble
    phys = PhysicsSpec.of(sim)
    if fit == "E":
        amb = PUNYO_BAROMETRIC_AMBIENT_PA if ambient_pa is None else ambient_pa
        phys = replace(phys, atmospheric_pa=amb, gauge_pressure_pa=p_rest - amb)
    assert real.centre_m is not None  # hold_summary keeps frames with a centre only
    at = (real.centre_m[0], real.centre_m[1])
    press_depth = real.depth_m * 1.35
    if radius_m is None:
        radius_m = _matched_radius(phys, at, press_depth, real, log)
    rad = float(radius_m)
    dent = _DentTarget(at, rad, press_depth, real, p_rest, apex)
    x0 = float(np.log(phys.gauge_pressure_pa if fit == "gauge" else phys.youngs_modulus_pa))
    for _ in range(2):
        x0, p, rd = _fit_force(fit, phys, dent, x0, 0.5, log)
        s = at_dent(rd, real.depth_m)
        v_eff = p_rest * s.volume_m3 / s.dp_pa
        v_target = p_rest * real.volume_m3 / real.dp_pa
        vc = max(p.chamber_volume_m3 + (v_target - v_eff), 1e-6)
        log(f"  chamber volume {p.chamber_volume_m3 * 1e6:.0f} -> {vc * 1e6:.0f} cm3")
        phys = replace(phys, chamber_volume_m3=round(vc, 7))
    x0, p, rd = _fit_force(fit, phys, dent, x0, 0.05, log)
    return Identified(
        real=real,
        real_apex_m=apex,
        sim=at_dent(rd, real.depth_m),
        sim_dp_at_real_force_pa=dp_at_force(rd, real.force_n),
        sim_apex_m=inflated_apex(p),
        physics=p,
        radius_m=rad,
    )


@dataclass(frozen=True)
class _DentTarget:
    """What a trial press must reproduce: the real dent (centre, depth, force) pressed by a
    sphere of ``radius_m`` to ``press_depth_m``, on a bubble at the real rest pressure/apex."""

    at: tuple[float, float]
    radius_m: float
    press_depth_m: float
    real: PressSummary
    p_rest: float
    apex: float


def _fit_force(
    fit: str, phys: Any, dent: _DentTarget, x0: float, step: float, log: Any
) -> tuple[float, Any, list[DentReading]]:
    """Secant on log force over the log trial value (from ``x0``, first step ``step``) until
    the simulated press gives the real force at the real dent depth; returns the log value,
    its physics and its dent readings."""
    runs: dict[float, tuple[Any, list[DentReading]]] = {}

    def force_of(log_x: float) -> float:
        p = _trial_physics(fit, phys, float(np.exp(log_x)), dent.p_rest, dent.apex)
        rd = sim_press(press_scene(p, dent.at, dent.radius_m, dent.press_depth_m))
        runs[log_x] = (p, rd)
        s = at_dent(rd, dent.real.depth_m)
        log(
            f"  gauge {p.gauge_pressure_pa:.0f} Pa, E {p.youngs_modulus_pa / 1e6:.3f} MPa, rest "
            f"dome {p.rest_dome_height_m * 1e3:.2f} mm, Vc {p.chamber_volume_m3 * 1e6:.0f} cm3: "
            f"|f| {s.force_n:.2f} N, dp {s.dp_pa:.0f} Pa, area {s.area_m2 * 1e4:.2f} cm2, "
            f"volume {s.volume_m3 * 1e6:.2f} cm3"
        )
        return float(np.log(s.force_n))

    x = _secant(force_of, x0, x0 + step, float(np.log(dent.real.force_n)), tol=0.01)
    p, rd = runs[x]
    return x, p, rd


def _matched_radius(
    phys: Any, at: tuple[float, float], press_depth: float, real: PressSummary, log: Any
) -> float:
    """The sphere radius (m, rounded to 0.1 mm) whose dent on ``phys`` covers the real dent's
    area (deeper than 2 mm) at the real depth: secant on log radius."""

    def area_of(log_r: float) -> float:
        r = float(np.exp(log_r))
        s = at_dent(sim_press(press_scene(phys, at, r, press_depth)), real.depth_m)
        log(
            f"  sphere {r * 1e3:.2f} mm: area {s.area_m2 * 1e4:.2f} cm2, volume "
            f"{s.volume_m3 * 1e6:.2f} cm3 at the real depth"
        )
        return float(np.log(s.area_m2))

    r_fit = _secant(area_of, np.log(0.008), np.log(0.012), np.log(real.area_m2), tol=0.01)
    return round(float(np.exp(r_fit)), 4)


def _trial_physics(fit: str, phys: Any, value: float, p_rest: float, apex: float) -> Any:
    """``phys`` with the trial value (gauge pressure with E in proportion, or E alone) and the
    stress-free dome whose inflation gives the real rest apex (secant on ``inflated_apex``)."""
    from dataclasses import replace

    from bubble_rt.sensor import PROFILES

    if fit == "gauge":
        sim = PROFILES["sim"].bubble
        g = round(value, 1)
        e = round(sim.youngs_modulus_pa * g / sim.gauge_pressure_pa, -3)
        p = replace(
            phys, gauge_pressure_pa=g, atmospheric_pa=round(p_rest - g, 1), youngs_modulus_pa=e
        )
    else:
        p = replace(phys, youngs_modulus_pa=round(value, -3))

    def apex_of(h: float) -> float:
        return inflated_apex(replace(p, rest_dome_height_m=h))

    h = _secant(apex_of, 0.8 * apex, 0.9 * apex, apex, tol=2e-5)
    return replace(p, rest_dome_height_m=round(h, 6))


def estimator_on_press(
    scene: object,
    ambient_pa: float,
    youngs_modulus: float | None = None,
    mesh: str = "medium",
) -> list[tuple[float, float]]:
    """(true |f|, estimated |f|) in N on each frame of a simulated press, read by the default
    FEM estimator (configuration defaults, the ``ambient_pa`` and, if given, the linearised
    ``youngs_modulus`` (Pa) given) fitted on 5 untouched frames: how the estimator's linear
    model reads a bubble whose physics is known."""
    from dataclasses import replace

    from bubble_rt.estimation.estimator import EstimatorConfig, config_changes
    from bubble_rt.estimation.pipeline import Pipeline
    from bubble_rt.sim.simulator import Simulator

    sim = Simulator(scene)  # type: ignore[arg-type]
    values = {"ambient_pa": float(ambient_pa)}
    if youngs_modulus is not None:
        values["youngs_modulus"] = float(youngs_modulus)
    cfg = EstimatorConfig()
    config = replace(cfg, **config_changes(cfg, values))
    pipe = Pipeline.capture(sim.reference_frames(5), sim.camera, mesh=mesh, config=config)
    out = []
    for f in sim.frames():
        est = pipe.process(f)
        truth = float(np.linalg.norm(f.truth.net_force))  # type: ignore[union-attr]
        out.append((truth, float(np.linalg.norm(est.net_force))))
    return out


__all__ = [
    "AREA_DEPTH_M",
    "Identified",
    "PressSummary",
    "at_dent",
    "dome_gap",
    "dp_at_force",
    "estimator_on_press",
    "hold_summary",
    "identify",
    "press_scene",
    "real_rest_apex",
    "DENT_FLOOR_M",
    "DentReading",
    "measure_dent",
    "press_readings",
    "real_press",
    "reference_depth",
    "sim_press",
]


if __name__ == "__main__":  # pragma: no cover - the identification's evidence (docs/sim-punyo.md)
    import argparse

    ap = argparse.ArgumentParser(description="identify a real press's physics")
    ap.add_argument("path", nargs="?", default="../shared/data/punyo-demo-0-press")
    ap.add_argument("--fit", choices=("gauge", "E"), default="gauge")
    ap.add_argument("--ambient-pa", type=float, default=None, help="with --fit E")
    ap.add_argument("--radius-m", type=float, default=None, help="default: fitted")
    a = ap.parse_args()
    print(identify(a.path, a.fit, a.ambient_pa, a.radius_m))
