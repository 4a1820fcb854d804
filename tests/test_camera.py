import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.mesh import Mesh


def test_d405_sees_the_whole_default_bubble():
    cam = Camera.d405()
    uv, z = cam.project(Mesh.preset("fine").vertices)
    assert (z > 0).all()
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < cam.width - 1).all()
    assert (uv[:, 1] > 0).all() and (uv[:, 1] < cam.height - 1).all()


@pytest.mark.parametrize("distortion", [(0, 0, 0, 0, 0), (-0.05, 0.01, 0.001, -0.002, 0.0)])
def test_project_backproject_round_trip(distortion):
    cam = Camera.d405(distortion=distortion)
    pts = Mesh.preset("coarse").vertices
    uv, z = cam.project(pts)
    back = cam.backproject(uv, z)
    assert np.abs(back - pts).max() < 1e-6


def test_pico_flexx_fov():
    cam = Camera.pico_flexx()
    assert np.degrees(2 * np.arctan(cam.width / 2 / cam.fx)) == pytest.approx(62, abs=0.5)
    assert np.degrees(2 * np.arctan(cam.height / 2 / cam.fy)) == pytest.approx(45, abs=0.5)


def test_invalid_camera_is_clear():
    with pytest.raises(ValueError, match="fx"):
        Camera.d405(fx=-1.0)
    with pytest.raises(ValueError, match="rotation"):
        Camera.d405(pose=((2, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1)))


def test_depth_to_points_marks_invalid():
    cam = Camera.pico_flexx()
    depth = np.full((cam.height, cam.width), 0.1, np.float32)
    depth[0, 0] = 0
    pts = cam.depth_to_points(depth)
    assert np.isnan(pts[0]).all()
    assert np.allclose(cam.to_camera(pts[1:2])[:, 2], 0.1)
