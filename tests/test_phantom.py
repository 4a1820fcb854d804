"""No phantom forces (issue 18 item 5): a depth jump the flow does not show is rejected by the
tracker (FLAG_DEPTH_JUMP) and filled, whatever the sensor profile.

Real: every untouched shared Punyo frame reads |f| < 0.3 N and no contact node with the
``punyo`` and the ``sim`` profiles, the phantom frame (punyo-demo-0-press index 7, a node lifted
19 mm with all its neighbours unmeasured) on its own. Simulator: a depth patch around one
peripheral node's projection moved by 19 mm (RGB, hence the flow, unchanged) on an untouched
and on a pressed frame. docs/phantom-forces.md has the numbers.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bubble_rt import eval as ev
from bubble_rt.config import DaemonConfig
from bubble_rt.estimation.deformation import FLAG_DEPTH_JUMP, FlowSettings
from bubble_rt.estimation.lifting import harmonic_fill, leave_one_out_residual, mesh_laplacian
from bubble_rt.estimation.pipeline import Pipeline, capture_settings
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh

pytestmark = pytest.mark.timeout(300)
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
UNTOUCHED = SHARED / "punyo-demo-0"
PRESS = SHARED / "punyo-demo-0-press"
PROFILES = ("punyo", "sim")
#: the issue's targets on untouched frames
MAX_FORCE_N = 0.3
#: the real depth jump and the one injected in the simulator, metres
JUMP_M = 0.019
needs_real = pytest.mark.skipif(not PRESS.exists(), reason="shared real data absent")


# ---------------------------------------------------------------- real untouched frames
@functools.cache
def _real(folder: str, profile: str) -> dict[int, tuple[float, int, int]]:
    """index -> (|net force| N, contact nodes, depth-jump nodes) of every frame of ``folder``,
    reference 0-4, as ``bubble-rt estimate`` reads it with ``[estimator] profile``."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(SHARED / folder)
    cfg = DaemonConfig().with_overrides(**{"estimator.profile": profile})
    settings = capture_settings(cfg, realtime=False, layout=rec.layout)
    pipe = Pipeline.capture([rec[i] for i in range(5)], rec.camera, **settings)
    out = {}
    for i in range(20 if folder == UNTOUCHED.name else 15):
        d = pipe.deform(rec[i])
        e = pipe.solve(rec[i], d)
        jumps = int(np.count_nonzero(d.flags & FLAG_DEPTH_JUMP))
        out[i] = (float(np.linalg.norm(e.net_force)), int(e.contact.sum()), jumps)
    return out


def _assert_untouched(reads: dict[int, tuple[float, int, int]], frames: range) -> None:
    for i in frames:
        f, contact, _ = reads[i]
        assert f < MAX_FORCE_N, f"frame {i}: |f| {f:.2f} N"
        assert contact == 0, f"frame {i}: {contact} contact nodes"


@needs_real
@pytest.mark.parametrize("profile", PROFILES)
def test_real_untouched_recording_has_no_phantom_force(profile):
    _assert_untouched(_real(UNTOUCHED.name, profile), range(20))


@needs_real
@pytest.mark.parametrize("profile", PROFILES)
def test_real_press_untouched_frames_have_no_phantom_force(profile):
    _assert_untouched(_real(PRESS.name, profile), range(5, 15))


@needs_real
@pytest.mark.parametrize("profile", PROFILES)
def test_real_phantom_frame_7_depth_jump_is_rejected(profile):
    # One node near the image corner is lifted 19 mm with every neighbour unmeasured: the
    # neighbour-median outlier check cannot see it; the sim profile read 5.96 N on it.
    f, contact, jumps = _real(PRESS.name, profile)[7]
    assert jumps == 1
    assert f < MAX_FORCE_N and contact == 0


# ---------------------------------------------------------------- simulator
@functools.cache
def _trajectory(geometry: str, k: int) -> tuple[Any, Mesh]:
    traj = ev.simulate_trajectory(geometry, k, 8, ev.CALIB_SEED_BASE)
    return traj, ev.estimator_mesh("medium", traj)


def _peripheral_node(pipe: Pipeline, far_from: np.ndarray | None = None) -> int:
    """A visible interior node next to the rim (the furthest from ``far_from``, mesh frame)."""
    mesh, tr = pipe.mesh, pipe.tracker
    rim = np.zeros(mesh.n_nodes, bool)
    rim[mesh.boundary] = True
    ring = np.flatnonzero(~rim & (mesh.adjacency() @ rim > 0) & tr.visible)  # type: ignore[union-attr]
    if far_from is None:
        return int(ring[0])
    return int(ring[np.argmax(np.linalg.norm(mesh.vertices[ring] - far_from, axis=1))])


def _inject_jump(frame: Frame, pipe: Pipeline, node: int, jump_m: float, isolate: bool) -> Frame:
    """``frame`` with the (valid) depth of a 5-px patch around ``node``'s projection moved by
    ``jump_m`` (camera z; RGB, hence the flow, unchanged). ``isolate``: the depth around it,
    out to past its neighbours' projections, is missing, as around the real phantom node."""
    tr = pipe.tracker
    uv = tr.uv_ref  # type: ignore[union-attr]
    depth = np.array(frame.depth, dtype=np.float32, copy=True)
    rows, cols = np.mgrid[: depth.shape[0], : depth.shape[1]]
    r = np.hypot(cols - uv[node, 0], rows - uv[node, 1])
    patch = r <= 5
    if isolate:
        nb = np.flatnonzero(pipe.mesh.adjacency()[node].toarray().ravel())
        reach = np.linalg.norm(uv[nb] - uv[node], axis=1).max() + 24
        depth[(r <= reach) & ~patch] = 0.0
    if isolate:  # the island keeps a full depth patch (the frame's own may have dropouts)
        ref = np.asarray(pipe.reference.depth)
        depth[patch] = np.where(ref[patch] > 0, ref[patch], depth[patch])
    depth[patch & (depth > 0)] += jump_m
    return dataclasses.replace(frame, depth=depth)


def _pipeline(traj: Any, mesh: Mesh, **flow: Any) -> Pipeline:
    """The default pipeline on a simulated trajectory (medium mesh fitted once, cached)."""
    settings = FlowSettings(**flow)
    return Pipeline.capture(traj.reference_frames, traj.camera, mesh=mesh, fit=False, flow=settings)


def _read(pipe: Pipeline, frame: Frame) -> tuple[float, int, Any]:
    d = pipe.deform(frame)
    e = pipe.solve(frame, d)
    return float(np.linalg.norm(e.net_force)), int(e.contact.sum()), d


@pytest.mark.parametrize("sign", [1, -1], ids=["raised", "lowered"])
def test_sim_untouched_frame_with_isolated_depth_jump_reads_no_force(sign):
    traj, mesh = _trajectory("round", 1)
    untouched = traj.frames[0]
    assert np.linalg.norm(untouched.truth.net_force) == 0.0
    pipe = _pipeline(traj, mesh)
    node = _peripheral_node(pipe)
    f, contact, d = _read(pipe, _inject_jump(untouched, pipe, node, sign * JUMP_M, True))
    assert d.flags[node] & FLAG_DEPTH_JUMP
    assert f < MAX_FORCE_N and contact == 0, f"|f| {f:.2f} N, {contact} contact nodes"
    # Without the check the same frame is the real phantom: a force on one lone node.
    f_off, _, _ = _read(
        _pipeline(traj, mesh, jump_m=None), _inject_jump(untouched, pipe, node, sign * JUMP_M, True)
    )
    assert f_off > 1.0


def test_sim_isolated_node_at_its_true_depth_is_kept():
    # Unmeasured neighbours alone do not reject a node: only a jump does.
    traj, mesh = _trajectory("round", 1)
    pipe = _pipeline(traj, mesh)
    node = _peripheral_node(pipe)
    _, _, d = _read(pipe, _inject_jump(traj.frames[0], pipe, node, 0.0, True))
    assert d.valid[node]


def test_sim_slow_isolated_rise_follows_its_history_until_a_tare():
    # The node must disagree with its own recent history too: risen 4 mm per frame it is kept;
    # after set_reference its history is the reference again, and the 19 mm rise is a jump.
    traj, mesh = _trajectory("round", 1)
    pipe = _pipeline(traj, mesh)
    tracker = pipe.tracker
    assert tracker is not None
    node = _peripheral_node(pipe)
    for h in (0.004, 0.008, 0.012, 0.016, JUMP_M):
        d = tracker.track(_inject_jump(traj.frames[0], pipe, node, h, True))
        assert d.valid[node], f"rise {h * 1e3:.0f} mm rejected"
    tracker.set_reference(pipe.reference)
    d = tracker.track(_inject_jump(traj.frames[0], pipe, node, JUMP_M, True))
    assert d.flags[node] & FLAG_DEPTH_JUMP


@pytest.mark.parametrize("geometry", ["round", "point"])
def test_sim_press_with_far_depth_jump_keeps_its_force(geometry):
    traj, mesh = _trajectory(geometry, 1)
    k = int(np.argmax([np.linalg.norm(f.truth.net_force) for f in traj.frames]))
    clean, jumped = _pipeline(traj, mesh), _pipeline(traj, mesh)
    for frame in traj.frames[:k]:
        clean.deform(frame)
        jumped.deform(frame)
    f_clean, _, d = _read(clean, traj.frames[k])
    assert f_clean > 2.0
    pressed = np.average(mesh.vertices, axis=0, weights=np.linalg.norm(d.U, axis=1))
    node = _peripheral_node(jumped, far_from=pressed)
    f_jump, contact, dj = _read(jumped, _inject_jump(traj.frames[k], jumped, node, JUMP_M, True))
    assert dj.flags[node] & FLAG_DEPTH_JUMP
    assert contact > 0
    assert abs(f_jump - f_clean) < 0.1 * f_clean, f"{f_jump:.2f} N against {f_clean:.2f} N"


@pytest.mark.parametrize("k", [0, 1])
def test_sim_point_presses_reject_no_node(k):
    # A point load concentrates on few nodes: none of them is taken for a depth jump.
    traj, mesh = _trajectory("point", k)
    pipe = _pipeline(traj, mesh)
    for frame in traj.frames:
        assert not (pipe.deform(frame).flags & FLAG_DEPTH_JUMP).any()


def test_leave_one_out_residual_is_the_value_minus_the_fill_without_it():
    mesh = Mesh.preset("medium")
    L = mesh_laplacian(mesh)
    rng = np.random.default_rng(0)
    X = rng.normal(size=(mesh.n_nodes, 3))
    known = rng.random(mesh.n_nodes) > 0.3
    nodes = np.flatnonzero(known)[:15]
    r = leave_one_out_residual(L, X, known, nodes)
    for row, c in zip(r, nodes, strict=True):
        without = known.copy()
        without[c] = False
        np.testing.assert_allclose(row, X[c] - harmonic_fill(L, X, without)[c], atol=1e-9)


def test_jump_tolerance_must_be_positive_or_none():
    assert FlowSettings(jump_m=None).jump_m is None
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="jump_m"):
            FlowSettings(jump_m=bad)
