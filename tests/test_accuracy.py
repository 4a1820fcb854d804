"""Force magnitudes on simulated camera frames: a light and a firm touch, named.

The paper's estimate read 5-16 % of the truth under 1.1 N and marked no contact below about
3 N; these tests keep that from coming back. Trajectories of the paper's dataset procedure
with the *calibration* master seed (``bubble_rt.eval.tasks.CALIB_SEED_BASE``), rendered and
tracked like `bubble-rt eval` does, default EstimatorConfig, medium mesh.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from bubble_rt import eval as ev
from bubble_rt.estimation.estimator import EstimatorConfig

pytestmark = [pytest.mark.timeout(600), pytest.mark.slow]


@functools.cache
def _frames(geometry: str, trajectory: int) -> list[tuple[float, float, bool, float]]:
    """(|f_gt|, |f_est|, any contact node, contact IoU against the truth) per frame of an
    8-frame trajectory."""
    traj = ev.simulate_trajectory(geometry, trajectory, 8, ev.CALIB_SEED_BASE)
    mesh = ev.estimator_mesh("medium", traj)
    est = ev.build_estimator("fem", mesh, traj, EstimatorConfig())
    out = []
    for frame in traj.frames:
        e = est.process(frame)
        g = float(np.linalg.norm(frame.truth.net_force))
        iou = ev.contact_iou(e.contact, frame.truth.contact_mask(mesh))
        out.append((g, float(np.linalg.norm(e.net_force)), bool(e.contact.any()), iou))
    return out


def _run(geometry: str, trajectory: int) -> list[tuple[float, float, bool]]:
    """(|f_gt|, |f_est|, any contact node) per frame of an 8-frame trajectory."""
    return [(g, f, c) for g, f, c, _ in _frames(geometry, trajectory)]


def test_light_touch_is_detected_with_the_right_magnitude():
    # round-0 presses lightly: 0.49, 1.08, 1.07 N in its last three frames.
    light = [(g, f, c) for g, f, c in _run("round", 0) if 0.4 <= g <= 1.1]
    assert len(light) >= 2
    for g, f, c in light:
        assert c, f"{g:.2f} N touch not detected"
        assert 0.7 <= f / g <= 1.3, f"{g:.2f} N touch read {f:.2f} N"


@pytest.mark.parametrize("geometry", ["round", "square"])
def test_firm_touch_magnitude_within_15_percent(geometry):
    # round-1 / square-1 press firmly: 8.9 / 9.1 N in frame 5.
    firm = [(g, f, c) for g, f, c in _run(geometry, 1) if 7.0 <= g <= 13.0]
    assert firm
    for g, f, c in firm:
        assert c
        assert 0.85 <= f / g <= 1.15, f"{g:.2f} N press read {f:.2f} N"


def test_a_flat_faces_contact_covers_its_middle():
    """square-1 presses a flat face at 4.4-14.2 N. The membrane pressed flat carries only the
    gas's gauge pressure in the face's middle and line loads at its edges, so the contact
    rule's half-peak threshold kept the edges alone (IoU 0.19-0.40); each load's contact is
    filled to the convex hull of its nodes (IoU 0.44-0.76)."""
    firm = [iou for g, _, _, iou in _frames("square", 1) if g >= 4.0]
    assert len(firm) >= 3
    assert np.mean(firm) >= 0.5, firm
