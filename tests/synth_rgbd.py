"""Synthetic RGBD helpers for the deformation tests and bench (not a test module)."""

from __future__ import annotations

import cv2
import numpy as np
from bubble_rt.camera import Camera
from bubble_rt.mesh import MeshGeometry
from numpy.typing import NDArray


def texture(h: int, w: int, seed: int = 0) -> NDArray[np.uint8]:
    """A dot/speckle texture like the membrane's print, RGB uint8."""
    rng = np.random.default_rng(seed)
    grey = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.2, 1.0), (3.0, 0.8), (8.0, 0.5)):
        g = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        grey += amp * g / g.std()
    grey = (grey - grey.min()) / (grey.max() - grey.min())
    img = (grey * 220 + 20).astype(np.uint8)
    return np.dstack([img, (img * 0.9).astype(np.uint8), (img * 0.7).astype(np.uint8)])


def smooth_flow(h: int, w: int, amplitude: float = 3.0) -> NDArray[np.float32]:
    """A smooth H x W x 2 flow field (pixels), up to about ``amplitude`` px."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    fu = amplitude * np.sin(2 * np.pi * u / w * 1.2 + 0.3) * np.cos(2 * np.pi * v / h * 0.8)
    fv = 0.7 * amplitude * np.cos(2 * np.pi * u / w * 0.9) * np.sin(2 * np.pi * v / h + 0.5)
    return np.dstack([fu, fv]).astype(np.float32)


def warp(img: NDArray[np.uint8], flow: NDArray[np.float32]) -> NDArray[np.uint8]:
    """The image seen after every reference pixel p moved to p + flow(p)."""
    h, w = flow.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    pu, pv = u.copy(), v.copy()
    for _ in range(10):  # invert q = p + F(p) by fixed-point iteration
        f = cv2.remap(flow, pu, pv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        pu, pv = u - f[..., 0], v - f[..., 1]
    return cv2.remap(img, pu, pv, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def dome_depth(camera: Camera, g: MeshGeometry | None = None, offset: float = 0.0) -> NDArray:
    """Depth image (H x W float32, m) of the dome z = h (1 - r^2) (+ offset) seen by
    ``camera``, the rim plane outside the footprint."""
    g = g or MeshGeometry()
    uv = camera.pixel_grid()
    xy = camera.normalized(uv)
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    P = camera.pose_matrix
    o = P[:3, 3]
    d = d_cam @ P[:3, :3].T  # ray direction per unit camera z, mesh frame
    # Solve o_z + t d_z = H (1 - (o_x + t d_x)^2 / a^2 - (o_y + t d_y)^2 / b^2) + offset for t.
    a2, b2, H = g.semi_axis_x**2, g.semi_axis_y**2, g.dome_height
    A = H * (d[:, 0] ** 2 / a2 + d[:, 1] ** 2 / b2)
    B = d[:, 2] + 2 * H * (o[0] * d[:, 0] / a2 + o[1] * d[:, 1] / b2)
    C = o[2] - H * (1 - o[0] ** 2 / a2 - o[1] ** 2 / b2) - offset
    disc = np.maximum(B * B - 4 * A * C, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(A > 1e-12, (-B + np.sqrt(disc)) / (2 * A), -C / B)
    hit = o + t[:, None] * d
    r2 = hit[:, 0] ** 2 / a2 + hit[:, 1] ** 2 / b2
    t_plane = (offset - o[2]) / d[:, 2]
    t = np.where(r2 <= 1.0, t, t_plane)
    return t.reshape(camera.height, camera.width).astype(np.float32)


def centre_dent(
    camera: Camera, depth: NDArray, depth_m: float = 3e-3, sigma_px: float = 25.0
) -> NDArray[np.float32]:
    """``depth`` (H x W m) pushed towards the camera by a Gaussian dent of ``depth_m`` (m) and
    ``sigma_px`` (pixels) at the principal point; unread pixels (0) stay unread."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    r2 = (u - camera.cx) ** 2 + (v - camera.cy) ** 2
    dent = depth - depth_m * np.exp(-r2 / (2 * sigma_px**2))
    return np.where(depth > 0, dent, 0).astype(np.float32)


def blob_mask(h: int, w: int, fraction: float, seed: int = 1) -> NDArray[np.bool_]:
    """True on about ``fraction`` of the pixels, in smooth blobs."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 6.0)
    return noise > np.quantile(noise, 1.0 - fraction)
