"""RGBD deformation: flow sampling, depth back-projection, tracker, reference."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from bubble_rt.camera import Camera
from bubble_rt.estimation.deformation import (
    FLAG_FLOW_UNRELIABLE,
    FLAG_INVALID_DEPTH,
    FLAG_OUTSIDE_IMAGE,
    DeformationTracker,
    FlowSettings,
    Reference,
)
from bubble_rt.estimation.fitting import fit_mesh
from bubble_rt.estimation.lifting import (
    harmonic_fill,
    lift,
    lift_pixels,
    mesh_laplacian,
    neighbour_outliers,
    neighbour_table,
)
from bubble_rt.frames import Frame, FrameError
from bubble_rt.mesh import Mesh
from scipy.ndimage import map_coordinates
from synth_rgbd import blob_mask, dome_depth, smooth_flow, texture, warp


@pytest.fixture(scope="module")
def scene():
    cam = Camera.d405()
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    ref = Reference.capture(Frame(img, depth, 100000.0))
    mesh = fit_mesh(Mesh.preset("medium"), ref, cam)
    return cam, depth, img, ref, mesh


def true_flow_at(F: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.column_stack(
        [map_coordinates(F[..., c], [uv[:, 1], uv[:, 0]], order=1) for c in (0, 1)]
    )


def warp_flow(scene, settings: FlowSettings) -> tuple[np.ndarray, np.ndarray]:
    """Flow at the nodes (px) of the synthetic 3 px warp, and its error against the truth."""
    cam, depth, img, ref, mesh = scene
    F = smooth_flow(cam.height, cam.width, 3.0)
    tr = DeformationTracker(mesh, cam, ref, settings)
    flow = tr.track(Frame(warp(img, F), depth, 100000.0)).flow
    return flow, np.linalg.norm(flow - true_flow_at(F, tr.uv_ref), axis=1)


def flow_error(scene, method: str) -> np.ndarray:
    return warp_flow(scene, FlowSettings(method=method))[1]


def _warp_rms(scene, settings: FlowSettings) -> tuple[float, np.ndarray]:
    """RMS flow error at the nodes (px) of the synthetic warp, and the flow."""
    flow, err = warp_flow(scene, settings)
    return float(np.sqrt(np.mean(err**2))), flow


def _pixel_tracker(**overrides):
    """The C++ tracker (flow + depth fill) with DIS ultrafast and the given overrides."""
    from bubble_rt import _core

    kw = dict(
        method=1,
        dis_preset=0,
        pyr_scale=0.5,
        levels=3,
        winsize=15,
        iterations=3,
        poly_n=5,
        poly_sigma=1.2,
        gaussian=False,
        scale=1.0,
        forward_backward=False,
        refine_window=15,
    )
    return _core._PixelTracker(**{**kw, **overrides})


def test_flow_at_nodes_farneback_within_0_3_px(scene):
    err = flow_error(scene, "farneback")
    assert err.max() < 0.3


def test_flow_at_nodes_dis_medium_within_0_3_px(scene):
    err = flow_error(scene, "dis_medium")
    assert err.max() < 0.3


def test_refinement_at_the_nodes_beats_the_finer_dense_flow(scene):
    """The default flow is DIS at its preset's pyramid level 2, refined by Lucas-Kanade at each
    node (FlowSettings.refine_window_px): it must read the synthetic warp better than the dense
    field alone, at level 2 and at the twice finer level 1 the refinement replaced (measured:
    rms 0.049 px against 0.170 at level 2 and 0.068 at level 1)."""
    rms, flow = _warp_rms(scene, FlowSettings())
    rms_level2, dense = _warp_rms(scene, FlowSettings(refine_window_px=0))
    rms_level1, _ = _warp_rms(scene, FlowSettings(refine_window_px=0, dis_finest_scale=1))
    assert FlowSettings().refine_window_px == 15 and FlowSettings().dis_finest_scale is None
    assert rms < 0.4 * rms_level2 and rms < 0.8 * rms_level1, (rms, rms_level2, rms_level1)
    assert not np.array_equal(flow, dense)


def test_refinement_keeps_the_dense_flow_where_it_would_jump(scene):
    """A window that would move more than 2 px away from the dense flow keeps the dense flow:
    on a warp of 3 px the refinement stays within 2 px of DIS everywhere."""
    _, flow = _warp_rms(scene, FlowSettings())
    _, dense = _warp_rms(scene, FlowSettings(refine_window_px=0))
    assert np.linalg.norm(flow - dense, axis=1).max() < 2.0


def test_flow_downscaled_still_close(scene):
    cam, depth, img, ref, mesh = scene
    F = smooth_flow(cam.height, cam.width, 3.0)
    tr = DeformationTracker(mesh, cam, ref, FlowSettings(method="dis_medium", scale=0.5))
    d = tr.track(Frame(warp(img, F), depth, 100000.0))
    assert np.median(np.linalg.norm(d.flow - true_flow_at(F, tr.uv_ref), axis=1)) < 0.3


# ---------------------------------------------------------------- back-projection
def surface_scene(kind: str):
    cam = Camera.d405()
    uv = cam.pixel_grid()
    xy = cam.normalized(uv)
    if kind == "plane":  # z = z0 + a x + b y in the camera frame, tilted about 20 degrees
        z0, a, b = 0.09, 0.3, -0.2
        t = z0 / (1 - a * xy[:, 0] - b * xy[:, 1])
    else:  # sphere cap, centre on the optical axis, near side seen
        c, R = 0.16, 0.1
        d = np.column_stack([xy, np.ones(len(xy))])
        dd = (d * d).sum(axis=1)
        disc = c**2 - dd * (c**2 - R**2)
        t = np.where(disc > 0, (c - np.sqrt(np.maximum(disc, 0))) / dd, 0.0)
    depth = t.reshape(cam.height, cam.width).astype(np.float32)
    rng = np.random.default_rng(3)
    q = np.column_stack([rng.uniform(120, 520, 400), rng.uniform(90, 390, 400)])
    qn = cam.normalized(q)
    if kind == "plane":
        tq = z0 / (1 - a * qn[:, 0] - b * qn[:, 1])
    else:
        d = np.column_stack([qn, np.ones(len(qn))])
        dd = (d * d).sum(axis=1)
        tq = (c - np.sqrt(c**2 - dd * (c**2 - R**2))) / dd
    truth = cam.backproject(q, tq)
    return cam, depth, q, truth


@pytest.mark.parametrize("kind", ["plane", "sphere_cap"])
def test_backprojection_within_0_1_mm(kind):
    cam, depth, q, truth = surface_scene(kind)
    pts, flags = lift_pixels(depth, q, cam)
    assert (flags == 0).all()
    assert np.abs(pts - truth).max() < 1e-4


@pytest.mark.parametrize("kind", ["plane", "sphere_cap"])
def test_backprojection_with_30_percent_blob_holes_within_0_5_mm(kind):
    cam, depth, q, truth = surface_scene(kind)
    holes = blob_mask(cam.height, cam.width, 0.30)
    assert 0.28 < holes.mean() < 0.32
    depth = depth.copy()
    depth[holes] = 0.0
    pts, flags = lift_pixels(depth, q, cam, max_fill_level=8)
    in_hole = holes[np.rint(q[:, 1]).astype(int), np.rint(q[:, 0]).astype(int)]
    assert in_hole.sum() > 50  # the check really covers filled depth
    assert (flags == 0).all()
    assert np.abs(pts - truth).max() < 5e-4


def test_backprojection_flags_points_outside_image():
    cam, depth, _, _ = surface_scene("plane")
    pts, flags = lift_pixels(depth, np.array([[-5.0, 10.0], [100.0, 1e6], [np.nan, 3.0]]), cam)
    assert (flags != 0).all()
    assert np.isfinite(pts).all()


# ---------------------------------------------------------------- tracker
def test_identical_frames_give_zero_displacement(scene):
    cam, depth, img, ref, mesh = scene
    tr = DeformationTracker(mesh, cam, ref)
    d = tr.track(Frame(img.copy(), depth.copy(), 100000.0))
    assert d.valid_fraction == 1.0
    assert np.abs(d.U).max() < 2e-6
    assert d.dp == 0.0
    assert set(d.timings_ms) == {"flow", "lift", "fill"}
    assert all(v >= 0.0 for v in d.timings_ms.values())


@pytest.mark.parametrize("distorted", [False, True])
def test_one_call_tracking_equals_the_separate_steps_bit_for_bit(scene, distorted):
    """The tracker's one C++ call (depth fill beside the flow) gives exactly what flow,
    sampling, hole filling and lifting called one after the other give: a moved texture, a
    dented surface with 30 % holes, and a camera with and without lens distortion. The frame
    before it has other holes: the fill's buffers, kept from frame to frame, carry nothing
    over."""
    cam, depth, img, ref, mesh = scene
    if distorted:
        cam = replace(cam, distortion=(0.05, -0.02, 0.001, 0.0005, 0.0))
    F = smooth_flow(cam.height, cam.width, 3.0)
    cur_depth = depth + np.float32(0.001)
    cur_depth[blob_mask(cam.height, cam.width, 0.30)] = 0.0
    cur = Frame(warp(img, F), cur_depth, 100000.0)
    tr = DeformationTracker(mesh, cam, ref)
    before = depth.copy()
    before[blob_mask(cam.height, cam.width, 0.10, seed=7)] = 0.0
    tr.track(Frame(img, before, 100000.0))
    tr.reset_history()
    d = tr.track(cur)
    s = tr.settings
    tr._pixel_tracker.compute(np.ascontiguousarray(cur.rgb))
    flow, _fb, flags = tr._pixel_tracker.sample(tr.uv_ref, s.fb_threshold_px)
    flow = np.asarray(flow)
    flags = np.asarray(flags, np.uint8).copy()
    flags[~tr.visible] |= FLAG_OUTSIDE_IMAGE
    x_cur, lift_flags = lift(cur_depth, tr.uv_ref + flow, cam, s.max_fill_level, s.depth_smoothing)
    tr.reset_history()
    by_steps = tr.finish(x_cur - tr.x_ref, flags | lift_flags, d.dp, {}, flow)
    assert (lift_flags != 0).any() and (lift_flags == 0).sum() > 100  # holes and lifted nodes
    assert np.array_equal(d.flow, by_steps.flow)
    assert np.array_equal(d.flags, by_steps.flags)
    assert np.array_equal(d.U, by_steps.U)


def test_known_translation_of_texture_and_depth(scene):
    """Texture shifted 2 px right and the surface 1 mm further: U follows."""
    cam, depth, img, ref, mesh = scene
    F = np.zeros((cam.height, cam.width, 2), np.float32)
    F[..., 0] = 2.0
    cur = Frame(warp(img, F), depth + np.float32(0.001), 100050.0)
    d = DeformationTracker(mesh, cam, ref).track(cur)
    assert d.dp == pytest.approx(50.0)
    inner = mesh.interior & d.valid
    # Expected: the node's ray moved 2 px, then lifted 1 mm further along z.
    uv, z = cam.project(mesh.vertices)
    z_cur = map_coordinates(depth.astype(np.float64), [uv[:, 1], uv[:, 0] + 2.0], order=1) + 0.001
    expected = cam.backproject(uv + [2.0, 0.0], z_cur) - mesh.vertices
    assert np.abs(d.U[inner] - expected[inner]).max() < 2e-4


def test_nodes_outside_image_are_flagged_and_filled(scene):
    cam, depth, img, ref, mesh = scene
    # Shift the camera so a third of the mesh projects outside the image.
    pose = cam.pose_matrix.copy()
    pose[0, 3] = 0.04
    cam2 = cam.with_pose(pose)
    ref2 = Reference.capture(Frame(img, dome_depth(cam2), 1e5))
    tr = DeformationTracker(mesh, cam2, ref2)
    d = tr.track(Frame(img, dome_depth(cam2), 1e5))
    outside = (d.flags & FLAG_OUTSIDE_IMAGE) != 0
    assert outside.sum() > 30
    assert not d.valid[outside].any()
    assert 0.0 < d.valid_fraction < 0.9
    assert np.isfinite(d.U).all()


def test_all_invalid_depth_region_is_flagged_not_nan(scene):
    cam, depth, img, ref, mesh = scene
    cur_depth = depth.copy()
    cur_depth[:, : cam.width // 2] = 0.0  # left half has no depth at all
    d = DeformationTracker(mesh, cam, ref).track(Frame(img, cur_depth, 1e5))
    uv, _ = cam.project(mesh.vertices)
    deep_left = uv[:, 0] < cam.width / 2 - 40
    assert ((d.flags[deep_left] & FLAG_INVALID_DEPTH) != 0).all()
    assert np.isfinite(d.U).all()
    assert np.abs(d.U).max() < 1e-3  # filled from the (unmoved) right half


def test_nan_in_point_cloud_gives_finite_output(scene):
    cam, depth, img, ref, mesh = scene
    pts = cam.to_camera(cam.depth_to_points(depth))
    pts[::7] = np.nan
    pts[200 * 640 : 260 * 640] = np.nan  # a band of rows with no reading
    d = DeformationTracker(mesh, cam, ref).track(Frame.from_pointcloud(img, pts, 1e5, cam))
    assert np.isfinite(d.U).all()
    assert np.abs(d.U).max() < 1e-3


def test_wrong_size_frame_is_a_clear_error(scene):
    cam, depth, img, ref, mesh = scene
    tr = DeformationTracker(mesh, cam, ref)
    with pytest.raises(FrameError, match="differs from the camera's 640 x 480"):
        tr.track(Frame(img[:, :600].copy(), depth[:, :600].copy(), 1e5))


def test_frame_without_images_is_a_clear_error(scene):
    cam, depth, img, ref, mesh = scene
    with pytest.raises(FrameError, match="rgb is missing"):
        DeformationTracker(mesh, cam, ref).track(Frame(None, depth, 1e5))


def test_forward_backward_flags_scrambled_region(scene):
    cam, depth, img, ref, mesh = scene
    cur = img.copy()
    rng = np.random.default_rng(5)
    cur[150:330, 230:410] = rng.integers(0, 255, (180, 180, 3), dtype=np.uint8)
    settings = FlowSettings(method="dis_medium", forward_backward=True, outlier_m=None)
    d = DeformationTracker(mesh, cam, ref, settings).track(Frame(cur, depth, 1e5))
    uv, _ = cam.project(mesh.vertices)
    inside = (uv[:, 0] > 250) & (uv[:, 0] < 390) & (uv[:, 1] > 170) & (uv[:, 1] < 310)
    unreliable = (d.flags & FLAG_FLOW_UNRELIABLE) != 0
    assert unreliable[inside].mean() > 0.5
    assert not unreliable[~inside & (uv[:, 0] < 150)].any()
    assert np.isfinite(d.U).all()


class _Truth:
    def displace(self, points):
        return points + np.array([0.0, 0.0, 0.002]) * (points[:, 2:3] > 0.01)


def test_oracle_uses_ground_truth_without_images():
    mesh = Mesh.preset("coarse")
    ref = Reference.capture(Frame(None, None, 1000.0))
    from bubble_rt.sim.oracle import OracleTracker

    tr = OracleTracker(mesh, Camera.d405(), ref, FlowSettings(method="oracle"))
    d = tr.track(Frame(None, None, 1010.0, truth=_Truth()))
    expected = _Truth().displace(mesh.vertices) - mesh.vertices
    np.testing.assert_allclose(d.U, expected)
    assert d.dp == pytest.approx(10.0)
    assert d.valid_fraction == 1.0
    with pytest.raises(FrameError, match="truth is missing"):
        tr.track(Frame(None, None, 1010.0))


def test_harmonic_fill_reproduces_linear_field_and_zeroes_isolated_nodes():
    mesh = Mesh.preset("coarse")
    L = mesh_laplacian(mesh)
    V = mesh.vertices
    known = np.ones(mesh.n_nodes, bool)
    known[np.argsort(np.linalg.norm(V[:, :2], axis=1))[:20]] = False
    filled = harmonic_fill(L, np.where(known[:, None], V[:, :2], np.nan), known)
    # The uniform Laplacian is not exact for linear fields on irregular meshes; close enough.
    assert np.abs(filled[~known] - V[~known, :2]).max() < 3e-3
    assert np.isfinite(filled).all()
    none = harmonic_fill(L, np.full((mesh.n_nodes, 3), np.nan), np.zeros(mesh.n_nodes, bool))
    assert (none == 0).all()


def test_harmonic_fill_equals_the_solve_on_sliced_blocks():
    import scipy.sparse.linalg as spla

    mesh = Mesh.preset("medium")
    L = mesh_laplacian(mesh)
    rng = np.random.default_rng(5)
    X = rng.normal(size=(mesh.n_nodes, 3))
    for fraction in (0.01, 0.1, 0.5):  # the dense path (<= 150 unknown nodes) and the sparse one
        known = rng.random(mesh.n_nodes) >= fraction
        iu, ik = np.flatnonzero(~known), np.flatnonzero(known)
        Luu = L[iu][:, iu] + 1e-9 * np.eye(len(iu))
        want = X.copy()
        want[iu] = spla.spsolve(sp.csc_matrix(Luu), -(L[iu][:, ik] @ X[ik]))
        got = harmonic_fill(L, np.where(known[:, None], X, np.nan), known)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def _numpy_neighbour_outliers(U, measured, nb, tol, relative_tol=0.0):
    """The rule in NumPy (the implementation before cpp/neighbour_median.cpp): the median of
    the measured neighbours by sorting with NaN last."""
    ok = (nb >= 0) & measured[np.maximum(nb, 0)]
    G = np.where(ok[:, :, None], U[np.maximum(nb, 0)], np.nan)
    count = ok.sum(axis=1)
    G.sort(axis=1)
    rows = np.arange(len(U))
    lo = G[rows, np.maximum(count - 1, 0) // 2]
    hi = G[rows, np.maximum(count, 1) // 2 - (count == 0)]
    med = np.nan_to_num(0.5 * (lo + hi))
    dev = np.linalg.norm(U - med, axis=1)
    return (
        measured
        & (count >= 2)
        & (dev > np.maximum(tol, relative_tol * np.linalg.norm(med, axis=1)))
    )


def test_neighbour_outliers_find_spikes_and_match_the_numpy_median_rule():
    mesh = Mesh.preset("coarse")
    nb = neighbour_table(mesh_laplacian(mesh))
    rng = np.random.default_rng(3)
    V = mesh.vertices
    smooth = 2e-3 * np.column_stack([np.sin(80 * V[:, 0]), np.cos(60 * V[:, 1]), V[:, 0] * 40])
    spikes = rng.choice(mesh.n_nodes, 12, replace=False)
    U = smooth.copy()
    U[spikes, 2] += 5e-3
    # a spike next to another one still stands 5 mm from the median of its neighbours
    found = neighbour_outliers(U, np.ones(mesh.n_nodes, bool), nb, 2e-3)
    assert set(np.flatnonzero(found)) == set(spikes.tolist())
    for trial in range(20):  # odd and even neighbour counts, sparse and dense measurement
        measured = rng.random(mesh.n_nodes) < rng.uniform(0.2, 1.0)
        U = smooth + rng.normal(scale=1e-3, size=smooth.shape)
        U[rng.random(mesh.n_nodes) < 0.3] *= 4.0  # some nodes far out, some dented regions
        tol, rel = rng.uniform(0.5e-3, 3e-3), rng.choice([0.0, 0.5, 1.0])
        got = neighbour_outliers(U, measured, nb, tol, rel)
        assert got.dtype == bool and got.shape == (mesh.n_nodes,)
        assert np.array_equal(got, _numpy_neighbour_outliers(U, measured, nb, tol, rel)), trial


def test_a_pin_tip_in_a_deep_dent_is_kept_and_a_glitch_beside_it_is_not():
    """A firm pin press: the tip stands 5 mm deeper than its neighbours, which are themselves
    17 mm in (what the simulator's truth gives at 9 N, medium mesh). A flat 4 mm tolerance
    rejected the tip and the estimate put its force on the ring around it; a 5 mm glitch
    where the membrane has not moved is still rejected."""
    mesh = Mesh.preset("medium")
    nb = neighbour_table(mesh_laplacian(mesh))
    V, n = mesh.vertices, mesh.vertex_normals()
    tip = int(np.argmin(np.linalg.norm(V[:, :2] - [-0.012, 0.007], axis=1)))
    r = np.linalg.norm(V - V[tip], axis=1)
    depth = np.where(r > 0, np.clip(0.017 - 0.8 * (r - r[r > 0].min()), 0.0, None), 0.022)
    U = -depth[:, None] * n
    glitch = int(np.argmin(np.linalg.norm(V[:, :2] - [0.025, -0.015], axis=1)))
    assert depth[glitch] == 0.0 and depth[nb[glitch][nb[glitch] >= 0]].max() == 0.0
    U[glitch] += 0.005 * n[glitch]
    measured = np.ones(mesh.n_nodes, bool)
    settings = FlowSettings()
    flat = neighbour_outliers(U, measured, nb, settings.outlier_m)
    assert flat[tip] and flat[glitch]  # the flat rule: both rejected
    kept = neighbour_outliers(U, measured, nb, settings.outlier_m, settings.outlier_relative)
    assert np.flatnonzero(kept).tolist() == [glitch]


def test_neighbour_outliers_bad_input_is_a_value_error():
    from bubble_rt import _core

    U, measured = np.zeros((3, 3)), np.ones(3, bool)
    with pytest.raises(ValueError, match="out of range"):
        _core._neighbour_outliers(U, measured, np.array([[1, 3], [0, 2], [0, 1]]), 1e-3)
    with pytest.raises(ValueError, match="N = 3"):
        _core._neighbour_outliers(U, np.ones(4, bool), np.zeros((3, 2), np.int64), 1e-3)
    with pytest.raises(ValueError, match="N x 3"):
        _core._neighbour_outliers(np.zeros((3, 2)), measured, np.zeros((3, 2), np.int64), 1e-3)


def test_reference_capture_averages_valid_depth_only():
    rgb1 = np.full((4, 5, 3), 10, np.uint8)
    rgb2 = np.full((4, 5, 3), 20, np.uint8)
    d1 = np.full((4, 5), 0.10, np.float32)
    d2 = np.full((4, 5), 0.12, np.float32)
    d1[0, 0] = 0.0
    d2[1, 1] = np.nan
    ref = Reference.capture([Frame(rgb1, d1, 100.0, t=1.0), Frame(rgb2, d2, 200.0, t=2.0)])
    assert ref.n_frames == 2 and ref.t == 2.0
    assert ref.pressure_pa == pytest.approx(150.0)
    assert ref.depth[0, 0] == pytest.approx(0.12)
    assert ref.depth[1, 1] == pytest.approx(0.10)
    assert ref.depth[2, 2] == pytest.approx(0.11)
    assert (ref.rgb == 15).all()
    tared = Reference.capture(Frame(rgb1, d1, 300.0))
    assert tared.pressure_pa == 300.0 and tared.n_frames == 1


def test_reference_capture_rejects_mixed_sizes():
    a = Frame(None, np.ones((4, 5), np.float32), 0.0)
    b = Frame(None, np.ones((4, 6), np.float32), 0.0)
    with pytest.raises(FrameError, match="differ in size"):
        Reference.capture([a, b])


def test_flow_settings_validation():
    with pytest.raises(ValueError, match="flow method"):
        FlowSettings(method="lucas_kanade")
    with pytest.raises(ValueError, match="scale"):
        FlowSettings(scale=1.5)
    heavy = FlowSettings(method="farneback_heavy").farneback_params()
    assert heavy["levels"] == 30 and heavy["winsize"] == 50 and heavy["poly_n"] == 7
    assert replace(FlowSettings(), levels=5).farneback_params()["levels"] == 5


def test_dis_output_never_reused_as_initial_guess(scene):
    """DIS treats a pre-sized output as its initial guess; the tracker must start fresh."""
    cam, depth, img, ref, mesh = scene
    F = smooth_flow(cam.height, cam.width, 3.0)
    moved = Frame(warp(img, F), depth, 1e5)
    tr = DeformationTracker(mesh, cam, ref, FlowSettings(method="dis_medium"))
    first = tr.track(moved).flow
    again = tr.track(moved).flow
    np.testing.assert_array_equal(first, again)
    still = tr.track(Frame(img, depth, 1e5))
    assert np.abs(still.flow).max() < 0.05


def test_set_reference_tares_the_tracker(scene):
    cam, depth, img, ref, mesh = scene
    F = np.zeros((cam.height, cam.width, 2), np.float32)
    F[..., 1] = 1.5
    moved = Frame(warp(img, F), depth, 100020.0)
    tr = DeformationTracker(mesh, cam, ref)
    assert np.abs(tr.track(moved).U).max() > 1e-4
    tr.set_reference(Reference.capture(moved))
    d = tr.track(moved)
    assert np.abs(d.U).max() < 2e-6
    assert d.dp == 0.0


# ---------------------------------------------------------------- with the estimator
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


def test_identical_frames_give_zero_force_and_no_contact(scene):
    from bubble_rt.estimation.pipeline import Pipeline

    cam, depth, img, ref, mesh = scene
    e = Pipeline(mesh, cam, ref).process(Frame(img.copy(), depth.copy(), 100000.0))
    assert not e.contact.any()
    assert np.linalg.norm(e.net_force) < 1e-3
    assert e.valid_node_fraction == 1.0
    assert {"flow", "lift", "solve"} <= set(e.timings_ms)


def test_pipeline_two_stages_match_the_tracker_and_estimator_by_hand(scene):
    from bubble_rt.estimation.estimator import ForceEstimator
    from bubble_rt.estimation.pipeline import Pipeline

    cam, depth, img, ref, mesh = scene
    F = np.zeros((cam.height, cam.width, 2), np.float32)
    F[..., 0] = 1.0
    frame = Frame(warp(img, F), depth, 100050.0)
    pipe = Pipeline(mesh, cam, ref)
    d = pipe.deform(frame)
    e = pipe.solve(frame, d)
    by_hand = DeformationTracker(mesh, cam, ref).track(frame)
    e_ref = ForceEstimator(mesh, reference=ref).estimate(by_hand.U, by_hand.dp)
    np.testing.assert_allclose(e.node_forces, e_ref.node_forces)
    assert e.valid_node_fraction == by_hand.valid_fraction == d.valid_fraction
    assert {"flow", "lift", "solve", "post"} <= set(e.timings_ms)
    np.testing.assert_allclose(Pipeline(mesh, cam, ref).process(frame).net_force, e.net_force)
    pipe.set_reference(Reference.capture(frame))
    assert np.abs(pipe.deform(frame).U).max() < 2e-6


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")
def test_real_untouched_frames_give_no_contact_and_small_force():
    from bubble_rt.estimation.pipeline import Pipeline
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(DATA)
    ref = Reference.capture([rec[i] for i in range(5)])
    mesh = fit_mesh(Mesh.preset("medium"), ref, rec.camera)
    pipe = Pipeline(mesh, rec.camera, ref)
    for i in range(5, 20):
        e = pipe.process(rec[i])
        assert not e.contact.any(), f"frame {i}: {int(e.contact.sum())} contact nodes"
        assert np.linalg.norm(e.net_force) < 0.5, f"frame {i}: |net force| {e.net_force}"
        assert e.valid_node_fraction > 0.7
        assert np.isfinite(e.displacements).all()


def test_core_input_errors_are_value_errors():
    from bubble_rt import _core

    with pytest.raises(ValueError, match="DIS preset"):
        _pixel_tracker(dis_preset=7)
    with pytest.raises(ValueError, match="poly_n"):
        _pixel_tracker(method=0, poly_n=6)
    for stride in (0, 9):  # 8 px patches
        with pytest.raises(ValueError, match="patch stride"):
            _pixel_tracker(dis_patch_stride=stride)
    for window in (3, 4, 16):  # odd and >= 5, or 0
        with pytest.raises(ValueError, match="refinement window"):
            _pixel_tracker(refine_window=window)
    of = _pixel_tracker()
    with pytest.raises(ValueError, match="no reference"):
        of.compute(np.zeros((20, 20, 3), np.uint8))
    of.set_reference(np.zeros((20, 20, 3), np.uint8), 0, 0, 20, 20)
    with pytest.raises(ValueError, match="size differs"):
        of.compute(np.zeros((20, 21, 3), np.uint8))
    with pytest.raises(ValueError, match="2-D"):
        _core._fill_depth(np.zeros((4, 4, 2), np.float32))


def test_flow_only_over_the_mesh_roi():
    cam = Camera.d405()
    pose = cam.pose_matrix.copy()
    pose[2, 3] = -0.16  # further away: the mesh covers the middle of the image only
    cam = cam.with_pose(pose)
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    ref = Reference.capture(Frame(img, depth, 1e5))
    mesh = fit_mesh(Mesh.preset("coarse"), ref, cam)
    tr = DeformationTracker(mesh, cam, ref, FlowSettings(margin_px=10))
    x0, y0, w, h = tr.roi
    uv, _ = cam.project(mesh.vertices)
    assert w < 0.7 * cam.width and h < 0.7 * cam.height
    assert x0 <= uv[:, 0].min() - 9 and x0 + w >= uv[:, 0].max() + 9
    F = smooth_flow(cam.height, cam.width, 2.0)
    d = tr.track(Frame(warp(img, F), depth, 1e5))
    assert d.valid_fraction == 1.0
    assert np.abs(d.flow - true_flow_at(F, tr.uv_ref)).max() < 0.3


def test_the_fill_kept_from_frame_to_frame_equals_a_fresh_one(scene):
    """The tracker's depth fill reuses its buffers: after frames with other holes, with none
    and with no valid pixel at all, each frame's filled depth is the one-shot fill's, bit for
    bit, everywhere (not only at the nodes)."""
    from bubble_rt import _core

    cam, depth, img, _ref, _mesh = scene
    rgb = np.ascontiguousarray(img)
    tr = _pixel_tracker()
    tr.set_reference(rgb, 0, 0, cam.width, cam.height)
    uv = np.array([[100.0, 100.0], [320.0, 240.0]])
    smoothing, max_level = 4, 3
    some = depth.copy()
    some[blob_mask(cam.height, cam.width, 0.30, seed=3)] = 0.0
    other = depth.copy()
    other[blob_mask(cam.height, cam.width, 0.05, seed=4)] = np.nan
    for d in (some, np.zeros_like(depth), other, depth, some):
        *_, filled, _ms = tr.track(rgb, d, uv, 1.0, smoothing, max_level, 1.0, 1.0, 0.0, 0.0, True)
        fresh, _level = _core._fill_depth(d, smoothing, max_level + 1)
        assert np.array_equal(filled, fresh)


def test_dis_field_stays_at_its_finest_level_and_a_tiny_image_still_tracks():
    """DIS is given images already reduced to its finest level (ultrafast: level 2), and its
    field is kept there; an image under 12 px at that level (DIS refuses those) is reduced by
    DIS itself. A 2 px shift reads 2 px either way."""
    for h, w, factor in ((120, 160, 4), (40, 36, 1)):
        grey = texture(h, w)[..., 0]
        ref = np.ascontiguousarray(np.dstack([grey] * 3))
        cur = np.ascontiguousarray(np.roll(ref, 2, axis=1))
        tr = _pixel_tracker(refine_window=0)
        tr.set_reference(ref, 0, 0, w, h)
        tr.compute(cur)
        field, _x0, _y0, scale = tr.dense()
        assert field.shape[:2] == (h // factor, w // factor) and scale == 1.0 / factor
        flow, _fb, flags = tr.sample(np.array([[w / 2, h / 2]]), 1.0)
        assert flags[0] == 0 and abs(flow[0, 0] - 2.0) < 0.5 and abs(flow[0, 1]) < 0.5
