"""Mesh fitting onto the reference depth surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.estimation.deformation import Reference
from bubble_rt.estimation.fitting import centre_pose, dome_apex, fit_mesh, surface_residuals
from bubble_rt.frames import Frame, FrameError
from bubble_rt.mesh import Mesh, MeshGeometry
from synth_rgbd import dome_depth, texture

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"
LOWER = MeshGeometry(dome_height=0.024)  # the observed dome is lower than the template's


def reference_for(cam: Camera, g: MeshGeometry) -> Reference:
    return Reference.capture(Frame(texture(cam.height, cam.width), dome_depth(cam, g), 1e5))


def check_fit(fitted: Mesh, template: Mesh, g: MeshGeometry) -> None:
    V = fitted.vertices
    assert fitted.n_nodes == template.n_nodes
    np.testing.assert_array_equal(fitted.triangles, template.triangles)
    np.testing.assert_array_equal(fitted.boundary, template.boundary)
    np.testing.assert_allclose(V[fitted.boundary], template.vertices[template.boundary])
    assert np.abs(V[:, 2] - g.height(V[:, 0], V[:, 1])).max() < 2e-4
    assert fitted.min_angle_deg() >= template.min_angle_deg() - 1.0


def test_fit_onto_synthetic_dome_within_0_2_mm():
    cam = Camera.d405()
    template = Mesh.preset("medium")
    fitted = fit_mesh(template, reference_for(cam, LOWER), cam)
    check_fit(fitted, template, LOWER)
    assert np.abs(fitted.vertices[:, 2] - template.vertices[:, 2]).max() > 4e-3  # really moved


def test_fit_with_tilted_camera():
    a = np.radians(15.0)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    pose[:3, 3] = [-0.02, 0.0, -0.07]
    cam = Camera.d405().with_pose(pose)
    template = Mesh.preset("coarse")
    fitted = fit_mesh(template, reference_for(cam, LOWER), cam)
    check_fit(fitted, template, LOWER)


def test_fit_ignores_an_occluder():
    cam = Camera.d405()
    ref = reference_for(cam, LOWER)
    depth = ref.depth.copy()
    depth[200:260, 280:340] = 0.03  # something between camera and membrane
    occluded = Reference(ref.rgb, depth, ref.pressure_pa)
    fitted = fit_mesh(Mesh.preset("medium"), occluded, cam)
    V = fitted.vertices
    assert np.abs(V[:, 2] - LOWER.height(V[:, 0], V[:, 1])).max() < 3e-3


def test_fit_needs_depth_of_camera_size():
    cam = Camera.d405()
    with pytest.raises(FrameError, match="depth is missing"):
        fit_mesh(Mesh.preset("coarse"), Reference(None, None, 0.0), cam)
    small = Reference(None, np.ones((10, 10), np.float32), 0.0)
    with pytest.raises(FrameError, match="differs from the camera's"):
        fit_mesh(Mesh.preset("coarse"), small, cam)


def test_fitted_mesh_save_load_round_trip(tmp_path):
    cam = Camera.d405()
    fitted = fit_mesh(Mesh.preset("coarse"), reference_for(cam, LOWER), cam)
    fitted.save(tmp_path / "fitted.vtk")
    loaded = Mesh.load(tmp_path / "fitted.vtk")
    np.testing.assert_allclose(loaded.vertices, fitted.vertices)
    np.testing.assert_array_equal(loaded.boundary, fitted.boundary)


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")
def test_fit_real_recording_nodes_on_observed_surface():
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(DATA)
    ref = Reference.capture([rec[i] for i in range(5)])
    template = Mesh.preset("medium")
    fitted = fit_mesh(template, ref, rec.camera)
    r = surface_residuals(fitted, ref, rec.camera)
    seen = np.isfinite(r)
    assert seen[fitted.interior].mean() > 0.85
    assert np.median(np.abs(r[seen])) < 1e-4
    assert np.percentile(np.abs(r[seen & fitted.interior]), 95) < 1e-3
    assert fitted.min_angle_deg() > 15.0
    # Same surface as the public implementation's own 390-node mesh (its frame: rim plane at
    # z = 0.054 m, footprint centre at x = 0.04025 m).
    import meshio

    P = np.asarray(meshio.read(DATA / "reference-mesh-390.vtk").points) - [0.04025, 0.0, 0.054]
    from scipy.interpolate import LinearNDInterpolator

    z = LinearNDInterpolator(fitted.vertices[:, :2], fitted.vertices[:, 2])(P[:, :2])
    inner = np.isfinite(z) & (P[:, 2] > 0.005)
    assert inner.sum() > 200
    assert np.median(np.abs(z[inner] - P[inner, 2])) < 1.5e-3


def test_centre_pose_recovers_in_plane_offset():
    """The dome is rendered with the true pose; the camera starts 3 mm and 4 degrees off."""
    cam = Camera.d405()
    depth = dome_depth(cam, LOWER)
    a = np.radians(4.0)
    off = np.eye(4)
    off[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    off[:2, 3] = [0.003, -0.002]
    wrong = cam.with_pose(off @ cam.pose_matrix)
    apex, yaw, ratio = dome_apex(depth, wrong)
    assert np.hypot(*apex[:2]) > 2e-3 and abs(np.degrees(yaw)) > 3.0
    fixed = centre_pose(wrong, depth)
    np.testing.assert_allclose(fixed.pose_matrix, cam.pose_matrix, atol=2e-4)
    apex, yaw, ratio = dome_apex(depth, fixed)
    assert np.hypot(*apex[:2]) < 1e-4
    assert apex[2] == pytest.approx(LOWER.dome_height, abs=2e-4)
    assert ratio == pytest.approx((LOWER.semi_axis_y / LOWER.semi_axis_x) ** 2, rel=0.05)


def test_centre_pose_refuses_a_wrong_initial_pose():
    cam = Camera.d405()
    depth = dome_depth(cam, LOWER)
    off = np.eye(4)
    off[0, 3] = 0.03
    with pytest.raises(FrameError, match="too far"):
        centre_pose(cam.with_pose(off @ cam.pose_matrix), depth)


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")
def test_real_recording_placement_from_data():
    from bubble_rt.io.recordings import open_recording, punyo_pose

    rec = open_recording(DATA)
    # The in-plane correction over the public placement is small ...
    delta = rec.camera.pose_matrix @ np.linalg.inv(punyo_pose())
    assert np.hypot(delta[0, 3], delta[1, 3]) < 2e-3
    # ... and every frame's dome apex then sits over the footprint centre.
    for i in (0, 10, 19):
        apex, yaw, ratio = dome_apex(rec[i].depth, rec.camera)
        assert np.hypot(*apex[:2]) < 5e-4
        assert abs(np.degrees(yaw)) < 1.0
        assert 0.025 < apex[2] < 0.035
        assert 0.4 < ratio < 0.7  # the long axis really is x
