"""The paper's full per-frame pipeline (Farneback flow, depth lifting, CVXPY solve) as one object."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bubble_rt.reference.model import _as_mesh_arrays, contact_mask, net_force, normal_pressure
from bubble_rt.reference.problem import GroupLassoProblem

if TYPE_CHECKING:
    from bubble_rt.camera import Camera


@dataclass(frozen=True)
class ReferenceSettings:
    """Settings of the paper's per-frame pipeline (public implementation's values).

    Farneback: pyr_scale 0.5, levels 30, winsize 50, iterations 5, poly_n 7, poly_sigma 1.5,
    Gaussian window, grey image. Point-cloud filter: keep points whose mesh-frame height above
    the mesh's lowest point (the rim plane) is in [-z_tol, max_height + z_tol] (m) and drop statistical outliers (mean distance to ``outlier_neighbors``
    neighbours above mean + ``outlier_std_ratio`` std; the public code uses Open3D with 200
    neighbours; 0 disables). ``cloud_stride`` subsamples the depth image before lifting
    (1 = every pixel, as the public code; larger = faster Delaunay in griddata).
    ``subtract_reference_lift``: U = S_cur(P(x)+F) - S_ref(P(x)) instead of S_cur(...) - x, so a
    mesh that does not lie exactly on the reference depth surface adds no bias (equal when it does).
    """

    pyr_scale: float = 0.5
    levels: int = 30
    winsize: int = 50
    iterations: int = 5
    poly_n: int = 7
    poly_sigma: float = 1.5
    max_height: float = 0.045
    z_tol: float = 0.002
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 3.0
    cloud_stride: int = 2
    subtract_reference_lift: bool = True
    tight: bool = False


class ReferencePipeline:
    """The paper's full per-frame pipeline: Farneback flow, griddata lifting, CVXPY solve.

    Args:
        vertices: N x 3 reference mesh nodes (mesh frame, metres).
        triangles: M x 3 node indices of the reference mesh's triangles.
        boundary: indices of the clamped rim nodes.
        camera: ``bubble_rt.camera.Camera`` (pose camera -> mesh).
        reference_rgb: H x W x 3 uint8 RGB of the untouched membrane.
        reference_depth: H x W float32 camera-z depth (m), 0 invalid.
        reference_pressure_pa: pressure of the reference (Pa).
        E: Young's modulus (Pa).
        nu: Poisson ratio.
        thickness: membrane thickness (m).
        k_f: force sparsity weight (1/N).
        k_u: displacement fit weight (1/m^2).
        k_const: contact threshold, constant term (Pa).
        k_linear: contact threshold, factor on the area-weighted mean pressure.
    """

    def __init__(
        self,
        vertices: ArrayLike,
        triangles: ArrayLike,
        boundary: ArrayLike,
        camera: Camera,
        reference_rgb: NDArray[np.uint8],
        reference_depth: NDArray[np.floating],
        reference_pressure_pa: float,
        E: float = 1.317e6,
        nu: float = 0.5,
        thickness: float = 0.65e-3,
        k_f: float = 0.3322,
        k_u: float = 537592.0,
        k_const: float = 2000.0,
        k_linear: float = 2.0,
        settings: ReferenceSettings | None = None,
    ) -> None:
        import cv2

        self.settings = settings or ReferenceSettings()
        self.vertices, self.triangles = _as_mesh_arrays(vertices, triangles)
        self.boundary = np.asarray(boundary, dtype=np.int64)
        self.camera = camera
        self.problem = GroupLassoProblem(
            self.vertices, self.triangles, self.boundary, E, nu, thickness, k_f, k_u
        )
        self.k_const = float(k_const)
        self.k_linear = float(k_linear)
        self.reference_pressure_pa = float(reference_pressure_pa)
        self._ref_grey = cv2.cvtColor(np.ascontiguousarray(reference_rgb), cv2.COLOR_RGB2GRAY)
        self._node_uv, _ = camera.project(self.vertices)
        if self.settings.subtract_reference_lift:
            self._x_ref = self._lift(np.asarray(reference_depth), self._node_uv)
        else:
            self._x_ref = self.vertices.copy()

    @classmethod
    def from_mesh(
        cls, mesh: Any, camera: Camera, reference: Any, **kwargs: Any
    ) -> ReferencePipeline:
        """Build from a ``Mesh`` and a reference with ``.rgb``, ``.depth``, ``.pressure_pa``."""
        return cls(
            mesh.vertices,
            mesh.triangles,
            mesh.boundary,
            camera,
            reference.rgb,
            reference.depth,
            reference.pressure_pa,
            **kwargs,
        )

    def _flow(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        import cv2

        s = self.settings
        grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        flow = cv2.calcOpticalFlowFarneback(  # type: ignore[call-overload]
            self._ref_grey,
            grey,
            None,
            s.pyr_scale,
            s.levels,
            s.winsize,
            s.iterations,
            s.poly_n,
            s.poly_sigma,
            cv2.OPTFLOW_FARNEBACK_GAUSSIAN,
        )
        return np.asarray(flow, dtype=np.float32)

    def _filtered_cloud(self, depth: NDArray) -> NDArray[np.float64]:
        from scipy.spatial import cKDTree

        s = self.settings
        st = max(int(s.cloud_stride), 1)
        H, W = depth.shape
        v, u = np.mgrid[0:H:st, 0:W:st]
        d = np.asarray(depth, dtype=np.float64)[v, u].ravel()
        ok = np.isfinite(d) & (d > 0)
        uv = np.column_stack([u.ravel()[ok], v.ravel()[ok]]).astype(np.float64)
        pts = self.camera.backproject(uv, d[ok])
        # Heights are measured from the mesh's lowest point (the rim plane in the mesh frame).
        z0 = float(self.vertices[:, 2].min())
        keep = (pts[:, 2] > z0 - s.z_tol) & (pts[:, 2] < z0 + s.max_height + s.z_tol)
        pts = pts[keep]
        k = int(s.outlier_neighbors)
        if k > 0 and len(pts) > k + 1:
            dd, _ = cKDTree(pts).query(pts, k=k + 1)
            # Sample spacing grows with camera distance; normalising by it keeps the far
            # (sparser) part of the dome from being taken for outliers.
            zc = np.maximum(self.camera.to_camera(pts)[:, 2], 1e-6)
            md = dd[:, 1:].mean(axis=1) / zc
            pts = pts[md <= md.mean() + s.outlier_std_ratio * md.std()]
        return pts

    def _lift(self, depth: NDArray, query_uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """S(query_uv): griddata over the projected filtered cloud plus the fixed rim nodes."""
        from scipy.interpolate import griddata

        pts = self._filtered_cloud(depth)
        # The clamped rim anchors the interpolation hull, as the public code does with its ellipse.
        rim = self.vertices[self.boundary]
        pts = np.vstack([pts, rim])
        uv, _ = self.camera.project(pts)
        out = np.asarray(griddata(uv, pts, query_uv, method="linear"))
        bad = ~np.all(np.isfinite(out), axis=1)
        if np.any(bad):
            out[bad] = np.asarray(griddata(uv, pts, query_uv[bad], method="nearest"))
        return out

    def process_frame(self, frame: Any) -> dict[str, Any]:
        """``process`` on a ``Frame`` (needs ``rgb``, ``depth`` and ``pressure_pa``)."""
        if frame.rgb is None or frame.depth is None:
            raise ValueError("the reference pipeline needs both rgb and depth images")
        return self.process(frame.rgb, frame.depth, frame.pressure_pa)

    def process(self, rgb: NDArray[np.uint8], depth: NDArray, pressure_pa: float) -> dict[str, Any]:
        """Run one frame; returns node_forces (N x 3, N), net_force (3,), contact (N,),
        normal_pressure (N,), displacements (N x 3 corrected, m), raw_displacements,
        objective, status and timings_ms {flow, lift, solve, post}."""
        t0 = time.perf_counter()
        flow = self._flow(rgb)
        t1 = time.perf_counter()
        from scipy.ndimage import map_coordinates

        uvn = self._node_uv
        fu = map_coordinates(flow[..., 0], [uvn[:, 1], uvn[:, 0]], order=1, mode="nearest")
        fv = map_coordinates(flow[..., 1], [uvn[:, 1], uvn[:, 0]], order=1, mode="nearest")
        x_cur = self._lift(np.asarray(depth), uvn + np.column_stack([fu, fv]))
        U = x_cur - self._x_ref
        U[self.boundary] = 0.0
        dp = float(pressure_pa) - self.reference_pressure_pa
        t2 = time.perf_counter()
        dU, obj = self.problem.solve(U, dp, tight=self.settings.tight)
        t3 = time.perf_counter()
        Uc = U + dU
        pb = self.problem
        F = pb.forces(Uc, dp)
        p = normal_pressure(F, pb.areas, pb.normals)
        contact = contact_mask(p, pb.areas, self.k_const, self.k_linear)
        f_net = net_force(F, self.boundary)
        t4 = time.perf_counter()
        return {
            "node_forces": F,
            "net_force": f_net,
            "contact": contact,
            "normal_pressure": p,
            "displacements": Uc,
            "raw_displacements": U,
            "dp": dp,
            "objective": obj,
            "status": pb.last_status,
            "timings_ms": {
                "flow": 1e3 * (t1 - t0),
                "lift": 1e3 * (t2 - t1),
                "solve": 1e3 * (t3 - t2),
                "post": 1e3 * (t4 - t3),
            },
        }
