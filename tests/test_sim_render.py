"""The simulator's rasteriser: exact depth, texture that moves with the material."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.sim.render import MembraneRenderer, render_depth


def grid_plane(z: float, half: float = 0.05, n: int = 40, tilt: float = 0.0):
    """A square plane mesh (n x n cells) at height z (+ tilt * x) in the mesh frame."""
    xs = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(xs, xs)
    V = np.column_stack([X.ravel(), Y.ravel(), z + tilt * X.ravel()])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    T = np.concatenate(
        [
            np.column_stack([a.ravel(), b.ravel(), d.ravel()]),
            np.column_stack([a.ravel(), d.ravel(), c.ravel()]),
        ]
    )
    return V, T.astype(np.int32)


def uv_sphere(centre, radius, n_lat=96, n_lon=192):
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    V = np.column_stack(
        [
            np.sin(TH).ravel() * np.cos(PH).ravel(),
            np.sin(TH).ravel() * np.sin(PH).ravel(),
            np.cos(TH).ravel(),
        ]
    )
    V = V * radius + np.asarray(centre)
    idx = np.arange((n_lat + 1) * n_lon).reshape(n_lat + 1, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    T = np.concatenate(
        [
            np.column_stack([a.ravel(), b.ravel(), d.ravel()]),
            np.column_stack([a.ravel(), d.ravel(), c.ravel()]),
        ]
    )
    return V, T.astype(np.int32)


def test_flat_plane_depth_is_exact():
    cam = Camera.d405()
    V, T = grid_plane(0.03)
    depth = render_depth(cam, V, T)
    hit = depth > 0
    # 100 mm square at 105 mm: 367 px wide
    assert abs(hit.sum(axis=1).max() - 0.1 * 385.263 / 0.105) < 2
    np.testing.assert_allclose(depth[hit], 0.105, atol=1e-6)


def test_tilted_plane_depth_matches_ray_intersection_within_0p1mm():
    cam = Camera.d405()
    V, T = grid_plane(0.02, tilt=0.3)
    depth = render_depth(cam, V, T)
    hit = depth > 0
    uv = cam.pixel_grid()
    xy = cam.normalized(uv)
    # Plane z_mesh = 0.02 + 0.3 x_mesh; camera frame = mesh frame shifted by 0.075 in z.
    z = (0.02 + 0.075) / (1.0 - 0.3 * xy[:, 0])
    err = np.abs(depth.ravel()[hit.ravel()] - z[hit.ravel()])
    assert err.max() < 1e-4
    assert err.max() < 1e-6  # planar triangles are exact up to float32


def test_sphere_depth_matches_analytic_within_0p1mm():
    cam = Camera.d405()
    c, r = np.array([0.005, -0.004, 0.03]), 0.02
    V, T = uv_sphere(c, r)
    depth = render_depth(cam, V, T).ravel().astype(np.float64)
    xy = cam.normalized(cam.pixel_grid())
    d = np.column_stack([xy, np.ones(len(xy))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = -cam.to_camera(c[None])[0]  # ray origin relative to the centre (camera frame)
    b = d @ o
    disc = b * b - (o @ o - r * r)
    ok = disc > (0.3 * r) ** 2  # away from the silhouette, where facets decide coverage
    s = -b[ok] - np.sqrt(disc[ok])
    z_true = s * d[ok, 2]
    assert ok.sum() > 10000
    assert (depth[ok] > 0).all()
    assert np.abs(depth[ok] - z_true).max() < 1e-4


def test_texture_moves_with_material_under_a_rigid_shift():
    cam = Camera.d405()
    V, T = grid_plane(0.03, half=0.06, n=30)
    ren = MembraneRenderer(cam, T, V[:, :2], shading=False)
    shift_px = 5
    dx = shift_px * 0.105 / cam.fx
    a = ren.render(V).rgb
    V2 = V.copy()
    V2[:, 0] += dx
    b = ren.render(V2).rgb
    # Same material at the same ray footprint: the image is the same, five pixels right.
    crop = np.s_[100:380, 150:500]
    diff = np.abs(b[crop[0], 155:505].astype(int) - a[crop].astype(int))
    assert diff.max() <= 1
    import cv2

    ga, gb = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (a, b))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(ga, gb, None)
    fu, fv = flow[crop][..., 0], flow[crop][..., 1]
    assert abs(np.median(fu) - shift_px) < 0.1
    assert abs(np.median(fv)) < 0.1


def test_rendering_is_deterministic_and_has_texture_detail():
    cam = Camera.d405()
    V, T = grid_plane(0.03, half=0.06, n=30)
    ren = MembraneRenderer(cam, T, V[:, :2])
    a, b = ren.render(V), ren.render(V)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    grey = a.rgb[100:380, 150:500].mean(axis=2)
    assert grey.std() > 20  # dense dots: enough contrast for optical flow


def test_depth_only_render_skips_texture():
    cam = Camera.d405()
    V, T = grid_plane(0.03)
    out = MembraneRenderer(cam, T, V[:, :2]).render(V, rgb=False)
    assert out.rgb is None
    assert (out.depth > 0).any()
    assert (out.face >= 0).sum() == (out.depth > 0).sum()


def test_bad_triangle_index_raises_value_error():
    cam = Camera.d405()
    V, T = grid_plane(0.03, n=2)
    T = T.copy()
    T[0, 0] = 1000
    with pytest.raises(ValueError, match="out of range"):
        render_depth(cam, V, T)


def test_distorted_camera_is_rejected():
    cam = Camera.d405(distortion=(0.1, 0, 0, 0, 0))
    V, T = grid_plane(0.03, n=2)
    with pytest.raises(ValueError, match="pinhole"):
        MembraneRenderer(cam, T, V[:, :2])
