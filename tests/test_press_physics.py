"""The dent measurement of bubble_rt.eval.press_physics on synthetic depth images whose dent is
known: a paraboloid pushed into a plane seen by a pinhole camera."""

from __future__ import annotations

import math

import numpy as np
from bubble_rt.camera import Camera
from bubble_rt.eval.press_physics import measure_dent, reference_depth

CAM = Camera.d405()
PLANE_Z = 0.08


def _dented(depth_m: float, radius_m: float, centre=(0.0, 0.0)) -> np.ndarray:
    """Depth image of the plane z = PLANE_Z with the paraboloid dent
    z = PLANE_Z - depth (1 - r^2 / radius^2) around the lateral point ``centre``."""
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    xn, yn = (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy
    z = np.full(xn.shape, PLANE_Z)
    for _ in range(30):  # the surface point on each ray: z = PLANE_Z - b(x(z), y(z))
        r2 = (xn * z - centre[0]) ** 2 + (yn * z - centre[1]) ** 2
        z = PLANE_Z - depth_m * np.clip(1 - r2 / radius_m**2, 0, None)
    return z.astype(np.float32)


def test_paraboloid_dent_depth_volume_and_area():
    ref = reference_depth([_dented(0.0, 0.01)] * 3)
    d, a = 5e-3, 0.015
    r = measure_dent(ref, _dented(d, a), CAM, dp_pa=400.0, force_n=4.0)
    assert abs(r.depth_m - d) < 0.1e-3  # on the optical axis the ray is the dent's axis
    assert abs(r.volume_m3 / (math.pi * a**2 * d / 2) - 1) < 0.03
    # Deeper than 2 mm: r^2 < a^2 (1 - 2/5) on the dent, counted where those rays meet the
    # reference plane, which is further from the camera by the 2 mm.
    seen = math.pi * a**2 * 0.6 * (PLANE_Z / (PLANE_Z - 2e-3)) ** 2
    assert abs(r.area_m2 / seen - 1) < 0.02
    assert r.centre_m is not None and np.allclose(r.centre_m[:2], CAM.pose_matrix[:2, 3], atol=1e-3)
    assert (r.dp_pa, r.force_n) == (400.0, 4.0)


def test_no_dent_and_unreadable_frames_give_zeros_not_nan():
    ref = reference_depth([_dented(0.0, 0.01)] * 3)
    flat = measure_dent(ref, _dented(0.0, 0.01), CAM)
    empty = measure_dent(ref, np.zeros((CAM.height, CAM.width), np.float32), CAM)
    for r in (flat, empty):
        assert (r.depth_m, r.area_m2, r.volume_m3) == (0.0, 0.0, 0.0)
        assert r.centre_m is None and r.centre_px is None


def test_depth_jumps_away_from_the_dent_do_not_count():
    """A patch jumping 10 mm towards the camera elsewhere (a mixed-pixel artefact: deeper than
    the dent, but small), and reference pixels that flicker between frames, leave the dent's
    reading as it was."""
    base = _dented(0.0, 0.01)
    flicker = base.copy()
    flicker[10:20, 10:20] -= 0.004
    ref = reference_depth([base, flicker, base])
    frame = _dented(4e-3, 0.012)
    clean = measure_dent(ref, frame, CAM)
    jumped = frame.copy()
    jumped[400:412, 550:562] -= 0.010
    jumped[10:20, 10:20] -= 0.006
    r = measure_dent(ref, jumped, CAM)
    assert np.isnan(ref[15, 15])
    assert (r.depth_m, r.volume_m3, r.area_m2) == (clean.depth_m, clean.volume_m3, clean.area_m2)
