"""Frame validation and constructors."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame, FrameError, pressure_to_pa

H, W = 12, 16


def small_camera() -> Camera:
    return Camera(fx=20.0, fy=20.0, cx=7.5, cy=5.5, width=W, height=H)


def rgb() -> np.ndarray:
    return np.zeros((H, W, 3), np.uint8)


def depth() -> np.ndarray:
    return np.full((H, W), 0.08, np.float32)


def test_valid_frame_keeps_fields():
    f = Frame(rgb(), depth(), 101325.0, t=1.5, index=3, wrench=np.arange(6.0))
    assert f.shape == (H, W)
    assert f.depth.dtype == np.float32
    assert f.wrench.shape == (6,)
    assert f.validate(small_camera()) is f


def test_float64_depth_is_converted_to_float32():
    f = Frame(None, depth().astype(np.float64), 0.0)
    assert f.depth.dtype == np.float32


def test_rgb_wrong_shape_names_rgb():
    with pytest.raises(FrameError, match="rgb"):
        Frame(np.zeros((H, W), np.uint8), depth(), 0.0)


def test_rgb_wrong_dtype_names_rgb():
    with pytest.raises(FrameError, match="rgb must be uint8"):
        Frame(np.zeros((H, W, 3), np.float32), depth(), 0.0)


def test_depth_integer_dtype_names_depth():
    with pytest.raises(FrameError, match="depth must be float"):
        Frame(rgb(), np.ones((H, W), np.uint16), 0.0)


def test_depth_wrong_ndim_names_depth():
    with pytest.raises(FrameError, match="depth must be H x W"):
        Frame(rgb(), np.ones((H, W, 1), np.float32), 0.0)


def test_rgb_depth_size_mismatch():
    with pytest.raises(FrameError, match="rgb size 16 x 12 differs from depth size 15 x 12"):
        Frame(rgb(), np.ones((H, W - 1), np.float32), 0.0)


def test_all_zero_depth_is_rejected():
    with pytest.raises(FrameError, match="depth has no valid pixel"):
        Frame(rgb(), np.zeros((H, W), np.float32), 0.0)


def test_all_nan_depth_is_rejected():
    with pytest.raises(FrameError, match="depth has no valid pixel"):
        Frame(rgb(), np.full((H, W), np.nan, np.float32), 0.0)


def test_nan_pressure_is_rejected():
    with pytest.raises(FrameError, match="pressure_pa"):
        Frame(rgb(), depth(), float("nan"))


def test_wrench_wrong_length():
    with pytest.raises(FrameError, match="wrench"):
        Frame(rgb(), depth(), 0.0, wrench=np.zeros(5))


def test_size_disagreeing_with_camera_names_field_and_camera():
    cam = Camera(fx=20.0, fy=20.0, cx=7.5, cy=5.5, width=W + 2, height=H)
    with pytest.raises(FrameError, match="rgb size 16 x 12 differs from the camera's 18 x 12"):
        Frame(rgb(), depth(), 0.0).validate(cam)


def test_validate_need_images():
    with pytest.raises(FrameError, match="rgb is missing"):
        Frame(None, depth(), 0.0).validate(need_images=True)


def test_pressure_units():
    assert pressure_to_pa(1065.8, "hPa") == pytest.approx(106580.0)
    assert pressure_to_pa(2.0, "kPa") == 2000.0
    assert pressure_to_pa(np.float64(5.0), "Pa") == 5.0
    with pytest.raises(FrameError, match="unit"):
        pressure_to_pa(1.0, "psi")


def test_from_pointcloud_zero_and_nan_points_are_invalid():
    cam = small_camera()
    v, u = np.mgrid[0:H, 0:W]
    z = 0.05 + 0.001 * u
    pts = np.dstack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z]).reshape(-1, 3)
    pts = pts.astype(np.float32)
    pts[5] = 0.0
    pts[7] = np.nan
    pts[9, 2] = 6.5535  # a saturated reading
    f = Frame.from_pointcloud(rgb(), pts, 1065.8, cam, pressure_unit="hPa", t=2.0, index=4)
    d = f.depth.ravel()
    assert d[5] == 0.0 and d[7] == 0.0 and d[9] == 0.0
    ok = np.ones(H * W, bool)
    ok[[5, 7, 9]] = False
    np.testing.assert_allclose(d[ok], z.ravel()[ok], rtol=1e-6)
    assert f.pressure_pa == pytest.approx(106580.0)
    assert (f.t, f.index) == (2.0, 4)


def test_from_pointcloud_wrong_point_count():
    with pytest.raises(FrameError, match="point cloud has 10 points"):
        Frame.from_pointcloud(rgb(), np.ones((10, 3)), 0.0, small_camera())


def test_from_pointcloud_all_invalid():
    pts = np.zeros((H * W, 3), np.float32)
    pts[::2] = np.nan
    with pytest.raises(FrameError, match="no valid point"):
        Frame.from_pointcloud(rgb(), pts, 0.0, small_camera())


def test_from_pointcloud_rgb_size_disagrees_with_camera():
    cam = small_camera()
    pts = np.ones((H * W, 3), np.float32) * 0.1
    with pytest.raises(FrameError, match="rgb size"):
        Frame.from_pointcloud(np.zeros((H, W + 1, 3), np.uint8), pts, 0.0, cam)


def test_from_uint16_applies_scale():
    raw = np.full((H, W), 800, np.uint16)
    raw[0, 0] = 0
    f = Frame.from_uint16(rgb(), raw, 1e-4, 5.0, pressure_unit="kPa", camera=small_camera())
    assert f.depth[0, 0] == 0.0
    assert f.depth[1, 1] == pytest.approx(0.08)
    assert f.pressure_pa == 5000.0


def test_from_uint16_rejects_float_depth_and_bad_scale():
    with pytest.raises(FrameError, match="uint16"):
        Frame.from_uint16(rgb(), depth(), 1e-3, 0.0)
    with pytest.raises(FrameError, match="depth_scale"):
        Frame.from_uint16(rgb(), np.ones((H, W), np.uint16), 0.0, 0.0)
