"""The simulator's camera effects reproduce the real D405's noise (docs/sim-noise.md).

The same statistics (bubble_rt.sim.sensor_stats) are measured on untouched real Punyo frames
(../shared/data/punyo-demo-0) and on untouched simulated frames seen from the Punyo's camera
pose, with the Punyo's membrane texture and the default D405 effects, and compared within
stated factors, each of which catches a 3x error:
- 1.5 on the hole fraction, the jump rate, the grey noise (overall, on flat areas and on
  edges), the overall depth noise, the depth noise smoothed over 1-4 mm, the flow noise on
  textured nodes and the RMS of the tracked nodes' lift;
- 1.25 on the flow noise against the real frames taken with the arm still;
- 1.15 on the image gradient at the textured nodes;
- 2 on the depth noise in every range bin (the real sensor's noise is not smooth in range);
- 2.5 on the nodes a jump lifts by more than 2 mm (a handful of events in 12 frames).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bubble_rt.io.punyo import punyo_pose
from bubble_rt.sensor import PUNYO_BUBBLE
from bubble_rt.sim import sensor_stats as ss

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "punyo-demo-0"
FRAMES = 12


@pytest.fixture(scope="module")
def real() -> ss.SensorStats:
    frames, cam = ss.real_frames(str(REAL), range(FRAMES))
    return ss.measure(frames, cam)


@pytest.fixture(scope="module")
def sim() -> ss.SensorStats:
    frames, cam = ss.sim_frames(FRAMES, camera_pose=punyo_pose(), texture=PUNYO_BUBBLE.texture)
    return ss.measure(frames, cam)


def within(a: float, b: float, factor: float) -> bool:
    return bool(np.isfinite(a) and np.isfinite(b) and b / factor <= a <= b * factor)


def test_depth_noise_against_range(real, sim):
    assert within(sim.noise_median_mm, real.noise_median_mm, 1.5)
    compared = 0
    for lo, r, s in zip(real.range_mm, real.noise_mm, sim.noise_mm, strict=False):
        if np.isfinite(r) and np.isfinite(s):
            assert within(s, r, 2.0), f"depth noise at {lo:.0f} mm: sim {s:.3f}, real {r:.3f}"
            compared += 1
    assert compared >= 5  # the membrane spans 60-100 mm with steady pixels on both sides


def test_depth_noise_survives_smoothing_as_the_real_one_does(real, sim):
    # Smoothed over 1-4 mm (the estimator reads depth at nodes 4-7 mm apart), the D405's noise
    # stays at 10-30 um: it is correlated over the stereo window. White noise of the same
    # per-pixel size falls to 1-5 um there, 9x under the real sensor at 4 mm.
    scales = zip(ss.SMOOTH_SCALES_M, real.smoothed_noise_mm, sim.smoothed_noise_mm, strict=True)
    for scale, r, s in scales:
        assert within(s, r, 1.5), f"smoothed over {scale * 1e3:.0f} mm: sim {s:.4f}, real {r:.4f}"


def test_depth_unit(real, sim):
    assert abs(real.step_mm - 0.1) < 0.01 and abs(sim.step_mm - real.step_mm) < 0.01


def test_holes_where_the_real_ones_are(real, sim):
    assert within(sim.hole_fraction, real.hole_fraction, 1.5)
    # Near-range limit: almost nothing valid below 55 mm, most valid past 60 mm.
    for z in (52.5, 57.5, 62.5, 72.5):
        assert within(sim.hole_at(z), real.hole_at(z), 1.5), f"holes at {z} mm"
    assert real.hole_at(92.5) < 0.01 and sim.hole_at(92.5) < 0.01
    # Holes stay put from frame to frame, as the real ones do.
    assert real.hole_persistence > 0.9 and sim.hole_persistence > 0.9


def test_depth_jumps(real, sim):
    assert within(sim.jump_rate, real.jump_rate, 1.5)
    # Under 60 mm the near-range limit makes them (elsewhere the real ones are mostly the
    # edges of the cable and label in view); half to two thirds read behind the surface.
    assert within(sim.jump_near_rate, real.jump_near_rate, 1.5)
    assert abs(sim.jump_near_behind - real.jump_near_behind) < 0.25
    assert within(sim.jump_mm[0], real.jump_mm[0], 1.5)  # median size, several mm
    assert within(sim.jump_mm[1], real.jump_mm[1], 1.5)  # 95th percentile, centimetres
    # Mostly on pixels that are otherwise holes, and at depth edges.
    assert sim.jump_in_holes > 0.7 and real.jump_in_holes > 0.7
    assert sim.jump_at_edges > 0.8 and real.jump_at_edges > 0.8


def test_image_noise_and_flow_on_textured_nodes(real, sim):
    assert within(sim.grey_noise, real.grey_noise, 1.5)
    assert within(sim.rgb_noise, real.rgb_noise, 1.5)
    # Flow noise on textured nodes, less the frame's rigid shift: the part image noise makes.
    # White noise on the dot texture made half the real one; the mosaic's noise on the
    # Punyo's texture makes 0.8 of it (docs/sim-noise.md, "Texture and image noise").
    assert within(sim.flow_textured_detrended_px, real.flow_textured_detrended_px, 1.5)
    assert sim.flow_textured_detrended_px < 0.1 and real.flow_textured_detrended_px < 0.1


def test_image_noise_is_stronger_on_edges_as_the_real_one_is(real, sim):
    # The D405's pipeline leaves 1.7x more noise on edges than on flat areas; white noise
    # leaves the same on both, which under-reads the noise the flow sees.
    assert within(sim.grey_noise_flat, real.grey_noise_flat, 1.5)
    assert within(sim.grey_noise_edges, real.grey_noise_edges, 1.5)
    assert real.grey_noise_edges > 1.3 * real.grey_noise_flat
    assert sim.grey_noise_edges > 1.3 * sim.grey_noise_flat


def test_texture_gives_the_flow_the_real_gradient(real, sim):
    # Where the flow is read (textured nodes), the image gradient sets its noise: the Punyo's
    # splashed paint gives 24-25 levels per pixel, the simulator's dots 31 (1.23x: fails).
    assert within(sim.node_gradient, real.node_gradient, 1.15)


def test_depth_jumps_lift_as_many_nodes_as_the_real_ones(real, sim):
    # Each tracked node's lift against its median over the frames: 0.5 nodes per frame lifted
    # by more than 2 mm on the real frames. Against the first frame's lift the simulator read
    # 1.6 (a jump in that one frame counted again in every later one; docs/sim-noise.md).
    assert within(sim.node_jump_rate, real.node_jump_rate, 2.5)
    assert within(sim.node_u_rms_mm, real.node_u_rms_mm, 1.5)


def test_flow_noise_matches_the_real_camera_with_the_arm_still(sim):
    # The real frames' flow noise grows while the arm moves (0.033 px still, 0.044-0.058 px in
    # motion: the membrane jiggles); with the arm still, the camera's noise alone is 0.033 px,
    # and the simulated camera's matches it (docs/sim-noise.md, "Flow noise with the arm still").
    still = ss.arm_still(str(REAL))
    assert still[:5] == [0, 1, 2, 3, 4]
    moving = [i for i in range(FRAMES) if i not in still]
    assert len(moving) >= 5

    def flow(indices: list[int]) -> float:
        frames, cam = ss.real_frames(str(REAL), indices)
        return ss.flow_stats(frames, cam)["flow_textured_detrended_px"]

    real_still, real_moving = flow(still), flow(moving)
    assert within(sim.flow_textured_detrended_px, real_still, 1.25)
    assert real_moving > 1.2 * real_still
