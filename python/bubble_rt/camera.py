"""Pinhole camera model with optional Brown-Conrady distortion and a pose in the mesh frame.

Camera frame: OpenCV convention (x right, y down, z forward), metres. ``pose`` is the 4 x 4
rigid transform from camera coordinates to mesh (sensor) coordinates: ``p_mesh = R p_cam + t``.
Depth images hold the camera-frame z (metres), 0 where invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray


def _default_pose() -> tuple[tuple[float, ...], ...]:
    # Camera 75 mm below the rim plane, looking up the sensor's +z axis; at that distance
    # the D405's field of view holds the whole 114.5 mm x 80 mm footprint.
    return (
        (1.0, 0.0, 0.0, 0.0),
        (0.0, 1.0, 0.0, 0.0),
        (0.0, 0.0, 1.0, -0.075),
        (0.0, 0.0, 0.0, 1.0),
    )


@dataclass(frozen=True)
class Camera:
    """Intrinsics (pixels), image size, distortion (k1, k2, p1, p2, k3) and pose.

    ``pose`` maps camera coordinates to mesh coordinates (4 x 4, metres).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    pose: tuple[tuple[float, ...], ...] = field(default_factory=_default_pose)

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(
                    f"camera {name} must be a positive focal length in pixels, got {v}"
                )
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width} x {self.height}")
        P = np.asarray(self.pose, dtype=np.float64)
        if P.shape != (4, 4) or not np.all(np.isfinite(P)):
            raise ValueError("camera pose must be a finite 4 x 4 matrix")
        R = P[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("camera pose rotation must be a proper rotation matrix")
        object.__setattr__(self, "pose", tuple(tuple(float(x) for x in row) for row in P))
        object.__setattr__(self, "distortion", tuple(float(x) for x in self.distortion))

    # ------------------------------------------------------------------ presets
    @classmethod
    def d405(cls, **overrides: object) -> Camera:
        """Intel RealSense D405 colour stream, 640 x 480 (one real unit's rectified intrinsics)."""
        base = cls(fx=385.263, fy=385.263, cx=307.943, cy=241.596, width=640, height=480)
        return replace(base, **overrides)  # type: ignore[arg-type]

    @classmethod
    def pico_flexx(cls, **overrides: object) -> Camera:
        """pmd Pico Flexx (the older Soft-bubble), 224 x 171, 62 x 45 degree field of view."""
        fx = 112.0 / np.tan(np.radians(31.0))
        fy = 85.5 / np.tan(np.radians(22.5))
        base = cls(fx=fx, fy=fy, cx=111.5, cy=85.0, width=224, height=171)
        return replace(base, **overrides)  # type: ignore[arg-type]

    @classmethod
    def preset(cls, name: str, **overrides: object) -> Camera:
        presets = {"d405": cls.d405, "pico_flexx": cls.pico_flexx}
        if name not in presets:
            raise ValueError(f"unknown camera preset {name!r}; choose one of {sorted(presets)}")
        return presets[name](**overrides)

    # ------------------------------------------------------------------ geometry
    @property
    def K(self) -> NDArray[np.float64]:
        """3 x 3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def pose_matrix(self) -> NDArray[np.float64]:
        """4 x 4 camera-to-mesh transform."""
        return np.asarray(self.pose, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.distortion)

    def to_camera(self, points_mesh: NDArray[np.float64]) -> NDArray[np.float64]:
        """Mesh-frame points (N x 3) to camera-frame points (N x 3), metres."""
        P = self.pose_matrix
        return (np.asarray(points_mesh, dtype=np.float64) - P[:3, 3]) @ P[:3, :3]

    def to_mesh(self, points_cam: NDArray[np.float64]) -> NDArray[np.float64]:
        """Camera-frame points (N x 3) to mesh-frame points (N x 3), metres."""
        P = self.pose_matrix
        return np.asarray(points_cam, dtype=np.float64) @ P[:3, :3].T + P[:3, 3]

    def project(self, points_mesh: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Pixel coordinates (N x 2, u right, v down) and camera depth z (N,) of mesh points."""
        pc = self.to_camera(points_mesh)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = pc[:, 0] / z
            y = pc[:, 1] / z
        if self.has_distortion:
            k1, k2, p1, p2, k3 = self.distortion
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = xd, yd
        uv = np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])
        return uv, z

    def normalized(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Undistorted normalised image coordinates (N x 2) of pixels (N x 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
        import cv2

        pts = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, np.asarray(self.distortion))
        return np.asarray(pts, dtype=np.float64).reshape(-1, 2)

    def backproject(self, uv: NDArray[np.float64], depth: NDArray[np.float64]) -> NDArray:
        """Mesh-frame points (N x 3) of pixels (N x 2) at camera depths z (N,), metres."""
        xy = self.normalized(uv)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        pc = np.column_stack([xy[:, 0] * z, xy[:, 1] * z, z])
        return self.to_mesh(pc)

    def pixel_grid(self) -> NDArray[np.float64]:
        """(H*W) x 2 pixel centres in row-major order."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        return np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)

    def depth_to_points(self, depth: NDArray) -> NDArray[np.float64]:
        """Organised mesh-frame point cloud (H*W x 3) of a depth image; NaN where depth <= 0."""
        d = np.asarray(depth, dtype=np.float64).reshape(-1)
        pts = self.backproject(self.pixel_grid(), d)
        pts[~(d > 0)] = np.nan
        return pts

    def with_pose(self, pose: NDArray[np.float64]) -> Camera:
        return replace(self, pose=tuple(tuple(float(x) for x in r) for r in np.asarray(pose)))
