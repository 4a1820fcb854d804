"""Frictionless baseline (Kuppuswamy et al., RA-L 2020) as the paper poses it (docs/method.md,
"Reference implementation and frictionless baseline").

A pre-tensioned membrane (constant tension T0) that moves only along its reference normals.
Unknowns: per interior node the normal displacement u_i (m) and the contact pressure pc_i <= 0
(Pa, negative pushes inward), plus the rise of the internal pressure pv (Pa). Rim: u = pc = 0.

    minimise    (1 / 2 N_r) sum_r w_r ((d0_r + (D u)_r - y_r) / sigma)^2
    subject to  T0 (L u)_i = a_i (pv + pc_i)          every interior node (equilibrium)
                pv = -(P0 / V0) sum_i a_i u_i           linearised isothermal gas
                pc_i <= 0

L is the P1 (cotangent) Laplacian of the reference mesh, each triangle in its own plane;
D_rj = S_rj / (n_r . r_hat_r) maps node displacements to the change of distance along
camera ray r (S: barycentric weights of the ray's hit on the reference mesh, n_r the
interpolated normal there); y_r is the observed distance along the ray (depth / cos), d0_r
the reference distance; w_r masks invalid pixels. T0 = p0 R / 2 (Young-Laplace) from the
rest gauge pressure p0 and the dome fitted to the mesh (R = (a^2 + h^2) / (2 h)).

The QP is solved by OSQP in non-dimensional variables (u / a, p a / T0, a = equivalent rim
half-width), each equilibrium row divided by its node's scaled area, Ruiz scaling and
polishing on. The ray set (pixel mask) is fixed at construction from the reference, so per
frame only q changes (and P's values when some pixels are invalid in that frame); OSQP warm
starts from the previous frame.

It cannot represent in-plane motion, shear or friction: net forces are sums of normal forces.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from bubble_rt.estimation.estimator import rest_gauge_pa
from bubble_rt.estimation.solver import SolverInfo
from bubble_rt.estimation.types import Estimate
from bubble_rt.mesh import lumped_areas, vertex_normals
from bubble_rt.reference import contact_mask, raycast_mesh
from bubble_rt.sensor import SIM, STANDARD_ATMOSPHERE_PA

__all__ = [
    "FrictionlessSettings",
    "FrictionlessEstimator",
    "cotangent_laplacian",
    "fit_dome",
    "DomeFit",
]

ATMOSPHERIC_PA = STANDARD_ATMOSPHERE_PA


@dataclass(frozen=True)
class FrictionlessSettings:
    """Settings of the frictionless baseline.

    Attributes:
        T0: membrane tension (N/m); None derives it as p0 R / 2 from the rest gauge pressure
            and the dome fitted to the mesh.
        rest_gauge_pa: rest gauge pressure p0 (Pa); None takes the reference pressure, minus
            the ambient pressure when it looks absolute (``estimator.rest_gauge_pa``, the
            FEM estimator's rule). Falls back to the configuration's ``inflation_pa`` (the
            sensor profile's rest gauge pressure) with a warning when that is not positive.
        atmospheric_pa: ambient pressure (Pa) for gauge <-> absolute; None: the estimator
            configuration's ``ambient_pa`` (the sensor profile's), else the standard one.
        chamber_depth: depth (m) of the air chamber behind the rim plane; the enclosed volume
            V0 = dome volume + footprint area * chamber_depth (None of ``chamber_volume``).
        chamber_volume: V0 (m^3) directly; overrides ``chamber_depth``.
        use_measured_pressure: fix pv to the measured pressure change instead of the gas row.
        sigma: depth noise (m) of the observation model.
        pixel_stride: use every stride-th pixel in both directions (speed).
        min_cos: drop rays meeting the reference surface at n . r_hat below this.
        reference_gate: drop pixels whose reference depth differs from the mesh by more (m).
        d0_from_depth: d0 = the reference depth image (True) or the mesh ray distance (False);
            the former removes any mismatch between mesh and reference surface.
        max_residual: per-frame, drop pixels whose distance changed by more than this (m).
        regularization: tiny Tikhonov weight on the non-dimensional unknowns (uniqueness
            where no ray sees a node).
        eps_abs, eps_rel, max_iter, polish, scaling, time_limit_s: OSQP settings
            (time_limit_s 0 = none).
    """

    T0: float | None = None
    rest_gauge_pa: float | None = None
    atmospheric_pa: float | None = None
    chamber_depth: float = 0.075
    chamber_volume: float | None = None
    use_measured_pressure: bool = False
    sigma: float = 1.5e-3
    pixel_stride: int = 4
    min_cos: float = 0.2
    reference_gate: float = 5e-3
    d0_from_depth: bool = True
    max_residual: float = 0.03
    regularization: float = 1e-6
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    max_iter: int = 4000
    polish: bool = True
    scaling: int = 10
    time_limit_s: float = 0.0


_STATUS = {
    "solved": "solved",
    "solved inaccurate": "solved",
    "maximum iterations reached": "max_iter_reached",
    "run time limit reached": "time_limit_reached",
}


# --------------------------------------------------------------------------- geometry
def cotangent_laplacian(vertices: NDArray, triangles: NDArray) -> sp.csr_matrix:
    """P1 (cotangent) Laplacian L (N x N, dimensionless, PSD), each triangle in its plane.

    ``u^T L u / 2 = integral |grad u|^2 / 2`` for the piecewise-linear u, so T0 L u is the
    membrane's restoring force (N) for normal displacements u (m).
    """
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    rows, cols, vals = [], [], []
    for m in range(3):
        i, j, k = T[:, m], T[:, (m + 1) % 3], T[:, (m + 2) % 3]
        e1, e2 = V[j] - V[i], V[k] - V[i]
        cot = np.einsum("ij,ij->i", e1, e2) / np.linalg.norm(np.cross(e1, e2), axis=1)
        w = 0.5 * cot  # weight of edge (j, k), opposite corner i
        rows += [j, k, j, k]
        cols += [k, j, j, k]
        vals += [-w, -w, w, w]
    n = len(V)
    L = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    return L.tocsr()


@dataclass(frozen=True)
class DomeFit:
    """Cap fitted to a mesh: rim plane, equivalent half-width a, height h, radius, volumes."""

    half_width: float
    height: float
    radius: float
    footprint_area: float
    dome_volume: float


def fit_dome(vertices: NDArray, triangles: NDArray, boundary: NDArray) -> DomeFit:
    """Rim plane by least squares, footprint = mesh projected on it, a = sqrt(area / pi)."""
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    rim = V[np.asarray(boundary, dtype=np.int64)]
    c = rim.mean(axis=0)
    normal = np.linalg.svd(rim - c)[2][-1]
    if normal @ vertex_normals(V, T).sum(axis=0) < 0:
        normal = -normal
    heights = (V - c) @ normal
    cr = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    proj_area = 0.5 * (cr @ normal)
    area = float(proj_area.sum())
    vol = float(proj_area @ heights[T].mean(axis=1))
    h = float(heights.max())
    a = float(np.sqrt(area / np.pi))
    return DomeFit(a, h, (a * a + h * h) / (2 * h), area, vol)


# --------------------------------------------------------------------------- estimator
class FrictionlessEstimator:
    """Kuppuswamy et al.'s frictionless estimator on depth images (OSQP).

    Args:
        mesh: ``Mesh`` (or anything with vertices N x 3, triangles T x 3, boundary).
        camera: ``bubble_rt.camera.Camera`` (pose camera -> mesh frame).
        reference: has ``.depth`` (H x W float32, m, 0 invalid) and ``.pressure_pa`` (Pa).
        config: an ``EstimatorConfig``-like object; its ``k_const`` / ``k_linear`` (contact
            threshold) are used when present (defaults 2000 Pa / 2).
        settings: ``FrictionlessSettings`` (None: defaults, or ``config.frictionless`` if set).
    """

    def __init__(
        self,
        mesh: Any,
        camera: Any,
        reference: Any,
        config: Any = None,
        settings: FrictionlessSettings | None = None,
    ) -> None:
        t_setup = time.perf_counter()
        if settings is None:
            settings = getattr(config, "frictionless", None) or FrictionlessSettings()
        self.settings = settings
        self.mesh = mesh
        self.config = config
        self.camera = camera
        self.k_const = float(getattr(config, "k_const", 2000.0))
        self.k_linear = float(getattr(config, "k_linear", 2.0))
        V = np.asarray(mesh.vertices, dtype=np.float64)
        T = np.asarray(mesh.triangles, dtype=np.int64)
        self.n = len(V)
        self.boundary = np.unique(np.asarray(mesh.boundary, dtype=np.int64))
        self.interior = np.setdiff1d(np.arange(self.n), self.boundary)
        self.areas = lumped_areas(V, T)
        self.normals = vertex_normals(V, T)
        self.reference_pressure_pa = float(reference.pressure_pa)
        self._membrane_constants(V, T, config)
        self._fix_rays(V, T, reference)
        self._observation_matrix()
        P = self._objective()
        self._setup_solver(P, self._constraints(V, T))
        self.setup_time_ms = 1e3 * (time.perf_counter() - t_setup)
        self.last_info: Any = None

    def _membrane_constants(self, V: NDArray, T: NDArray, config: Any) -> None:
        """Rest gauge pressure p0, tension T0 = p0 R / 2, absolute P0 and chamber volume V0."""
        s = self.settings
        self.dome = dome = fit_dome(V, T, self.boundary)
        ambient = s.atmospheric_pa
        if ambient is None:
            ambient = float(getattr(config, "ambient_pa", ATMOSPHERIC_PA))
        p0 = s.rest_gauge_pa
        if p0 is None:
            p0 = rest_gauge_pa(self.reference_pressure_pa, ambient)
        if p0 is None or not p0 > 0:
            fallback = float(getattr(config, "inflation_pa", SIM.bubble.gauge_pressure_pa))
            if s.T0 is None:
                warnings.warn(
                    f"the reference pressure {self.reference_pressure_pa} Pa gives no positive "
                    f"rest gauge pressure; using {fallback} Pa (the sensor profile's) for T0",
                    stacklevel=3,
                )
            p0 = fallback
        self.rest_gauge_pa = float(p0)
        self.T0 = float(s.T0) if s.T0 is not None else 0.5 * self.rest_gauge_pa * dome.radius
        self.P0 = self.rest_gauge_pa + ambient
        self.V0 = (
            float(s.chamber_volume)
            if s.chamber_volume is not None
            else dome.dome_volume + dome.footprint_area * s.chamber_depth
        )
        self.length = dome.half_width
        self.pressure_scale = self.T0 / self.length  # Pa per non-dimensional pressure unit

    def _fix_rays(self, V: NDArray, T: NDArray, reference: Any) -> None:
        """The ray set, fixed from the reference: every stride-th pixel that hits the mesh,
        meets it at n . r_hat >= min_cos and whose reference depth agrees with the mesh."""
        s, camera = self.settings, self.camera
        depth_ref = np.asarray(reference.depth, dtype=np.float64)
        if depth_ref.shape != (camera.height, camera.width):
            raise ValueError(
                f"reference depth is {depth_ref.shape}, camera is {camera.height} x {camera.width}"
            )
        hits = raycast_mesh(V, T, camera)
        st = max(int(s.pixel_stride), 1)
        sel = np.zeros(depth_ref.shape, dtype=bool)
        sel[::st, ::st] = True
        tri = hits.triangle
        ok = sel & (tri >= 0) & np.isfinite(depth_ref) & (depth_ref > 0)
        vv, uu = np.nonzero(ok)
        S = hits.bary[vv, uu]  # R x 3
        corners = T[tri[vv, uu]]  # R x 3
        n_r = np.einsum("rk,rkd->rd", S, self.normals[corners])
        n_r /= np.linalg.norm(n_r, axis=1, keepdims=True)
        cosn = np.einsum("rd,rd->r", n_r, hits.direction[vv, uu])
        xy = camera.normalized(np.column_stack([uu, vv]).astype(np.float64))
        cos_z = 1.0 / np.sqrt(1.0 + (xy**2).sum(axis=1))  # ray . camera z axis
        y_ref = depth_ref[vv, uu] / cos_z
        d_mesh = hits.distance[vv, uu]
        keep = (cosn >= s.min_cos) & (np.abs(y_ref - d_mesh) <= s.reference_gate)
        self._pix = (vv[keep], uu[keep])
        self._cos_z = cos_z[keep]
        self._d0 = (y_ref if s.d0_from_depth else d_mesh)[keep]
        self._ray_bary, self._ray_nodes, self._ray_cos = S[keep], corners[keep], cosn[keep]
        self.n_rays = len(self._d0)
        if self.n_rays == 0:
            raise ValueError("no camera ray sees the membrane in the reference depth image")

    def _observation_matrix(self) -> None:
        """Non-dimensional observation on interior nodes: residual = A x_u - b (R x ni)."""
        R, ni = self.n_rays, len(self.interior)
        col_of = np.full(self.n, -1, dtype=np.int64)
        col_of[self.interior] = np.arange(ni)
        self._ray_cols = cc = col_of[self._ray_nodes]
        self._ray_vals = vals = (
            (self.length / self.settings.sigma) * self._ray_bary / self._ray_cos[:, None]
        )
        m_int = cc >= 0
        rr = np.repeat(np.arange(R), 3).reshape(R, 3)
        self._A_obs = sp.csr_matrix((vals[m_int], (rr[m_int], cc[m_int])), shape=(R, ni))

    def _objective(self) -> sp.csc_matrix:
        """P's pattern, triu(A^T A) + the diagonal, and the map C from ray weights w to its
        values (P.data = C w / R + reg), so an invalid pixel changes only P's values."""
        ni = len(self.interior)
        self.nv = nv = 2 * ni + 1
        AtA = (self._A_obs.T @ self._A_obs).tocsc()
        pat = sp.triu(
            sp.block_diag([AtA, sp.csc_matrix((ni + 1, ni + 1))]) + sp.identity(nv), format="csc"
        )
        pat.sort_indices()
        pat_cols = np.repeat(np.arange(nv), np.diff(pat.indptr))
        keys = pat_cols * nv + pat.indices.astype(np.int64)
        self._C = self._weight_map(keys)
        diag_idx = np.searchsorted(keys, np.arange(nv) * nv + np.arange(nv))
        self._reg = np.zeros(len(keys))
        self._reg[diag_idx] = self.settings.regularization
        self._P_pattern = pat
        self._w = np.ones(self.n_rays)
        P = pat.copy()
        P.data = self._P_data(self._w)
        return P

    def _weight_map(self, keys: NDArray[np.int64]) -> sp.csr_matrix:
        """C (nnz(P) x R): entry (k, r) is ray r's contribution to P's k-th stored value."""
        cc, vals, nv = self._ray_cols, self._ray_vals, self.nv
        cr_, rr_, vv_ = [], [], []
        for p in range(3):
            for q in range(3):
                mk = (cc[:, p] >= 0) & (cc[:, q] >= 0) & (cc[:, p] <= cc[:, q])
                ridx = np.nonzero(mk)[0]
                k = cc[ridx, q] * nv + cc[ridx, p]
                pos = np.searchsorted(keys, k)
                if not np.array_equal(keys[np.minimum(pos, len(keys) - 1)], k):
                    raise RuntimeError("internal error: P pattern misses an observation pair")
                cr_.append(pos)
                rr_.append(ridx)
                vv_.append(vals[ridx, p] * vals[ridx, q])
        return sp.csr_matrix(
            (np.concatenate(vv_), (np.concatenate(cr_), np.concatenate(rr_))),
            shape=(len(keys), self.n_rays),
        )

    def _constraints(self, V: NDArray, T: NDArray) -> sp.csc_matrix:
        """Equilibrium rows (each divided by its node's scaled area), the gas row, pc <= 0."""
        s, a, ni = self.settings, self.length, len(self.interior)
        L = cotangent_laplacian(V, T)
        abar = self.areas[self.interior] / a**2
        L_II = sp.diags(1.0 / abar) @ L[self.interior][:, self.interior]
        I_n = sp.identity(ni)
        eq = sp.hstack([L_II, -I_n, -np.ones((ni, 1))])
        gamma = self.P0 * a * a / (self.V0 * self.T0)
        if s.use_measured_pressure:
            gas = sp.hstack([sp.csr_matrix((1, 2 * ni)), sp.csr_matrix([[1.0]])])
        else:
            gas = sp.hstack(
                [
                    sp.csr_matrix(gamma * self.areas[self.interior][None, :]),
                    sp.csr_matrix((1, ni)),
                    sp.csr_matrix([[1.0]]),
                ]  # fmt: skip
            )
        bound = sp.hstack([sp.csr_matrix((ni, ni)), I_n, sp.csr_matrix((ni, 1))])
        self._l = np.concatenate([np.zeros(ni + 1), np.full(ni, -np.inf)])
        self._u = np.zeros(2 * ni + 1)
        return sp.vstack([eq, gas, bound]).tocsc()

    def _setup_solver(self, P: sp.csc_matrix, Acon: sp.csc_matrix) -> None:
        """OSQP, set up once; per frame only q (and P's values) change."""
        import osqp

        s = self.settings
        extra: dict[str, Any] = {}
        if s.time_limit_s > 0:
            extra["time_limit"] = s.time_limit_s
        self._solver = osqp.OSQP()
        self._solver.setup(
            P,
            np.zeros(self.nv),
            Acon,
            self._l,
            self._u,
            **extra,
            eps_abs=s.eps_abs,
            eps_rel=s.eps_rel,
            max_iter=s.max_iter,
            polishing=s.polish,
            scaling=s.scaling,
            warm_starting=True,
            verbose=False,
        )

    def reconfigure(self, k_const: float | None = None, k_linear: float | None = None) -> None:
        """Change the contact threshold constants (Pa, -); the QP is unaffected."""
        if k_const is not None:
            self.k_const = float(k_const)
        if k_linear is not None:
            self.k_linear = float(k_linear)

    def _P_data(self, w: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(self._C @ w) / self.n_rays + self._reg

    # ------------------------------------------------------------------ per frame
    def estimate_depth(self, depth: NDArray, pressure_pa: float) -> Any:
        """Estimate from one depth image (H x W, camera z, m, 0/NaN invalid) and pressure (Pa).

        Returns an ``Estimate`` (node_forces N x 3 in N, contact_pressure N x 3 in Pa,
        normal_pressure N in Pa inward positive, contact, net_force, displacements N x 3 m).
        """
        t0 = time.perf_counter()
        w = self._update(depth, pressure_pa)
        t1 = time.perf_counter()
        res = self._solver.solve(raise_error=False)
        t2 = time.perf_counter()
        x = res.x
        if x is None or not np.all(np.isfinite(x)):
            x = np.zeros(self.nv)
        self.last_info = info = self._info(res.info)
        self.last_pv = float(x[-1]) * self.pressure_scale
        est = self._estimate(x, w, info)
        est.timings_ms = {
            "flow": 0.0,
            "lift": 1e3 * (t1 - t0),
            "solve": 1e3 * (t2 - t1),
            "post": 1e3 * (time.perf_counter() - t2),
        }
        return est

    def _update(self, depth: NDArray, pressure_pa: float) -> NDArray[np.float64]:
        """Pass the frame's observation to OSQP (q, and P's values when the valid pixels
        changed); returns the ray weights w (1 valid, 0 dropped)."""
        s = self.settings
        depth = np.asarray(depth)
        if depth.shape != (self.camera.height, self.camera.width):
            raise ValueError(
                f"depth is {depth.shape}, camera is {self.camera.height} x {self.camera.width}"
            )
        d = depth[self._pix].astype(np.float64)
        with np.errstate(invalid="ignore"):
            y = d / self._cos_z
            w = (np.isfinite(y) & (d > 0) & (np.abs(y - self._d0) <= s.max_residual)).astype(
                np.float64
            )
        b = np.where(w > 0, (np.nan_to_num(y) - self._d0) / s.sigma, 0.0)
        q = np.zeros(self.nv)
        ni = len(self.interior)
        q[:ni] = -(self._A_obs.T @ (w * b)) / self.n_rays
        update: dict[str, Any] = {"q": q}
        if not np.array_equal(w, self._w):
            update["Px"] = self._P_data(w)
            self._w = w
        if s.use_measured_pressure:
            dp = float(pressure_pa) - self.reference_pressure_pa
            if not np.isfinite(dp):
                raise ValueError(f"pressure must be finite, got {pressure_pa}")
            self._l[ni] = self._u[ni] = dp / self.pressure_scale
            update["l"], update["u"] = self._l, self._u
        self._solver.update(**update)
        return w

    @staticmethod
    def _info(info: Any) -> SolverInfo:
        return SolverInfo(
            status=_STATUS.get(str(info.status), str(info.status)),  # type: ignore[arg-type]  # an unmapped OSQP status passes through verbatim
            iterations=int(info.iter),
            primal_residual=float(info.prim_res),
            dual_residual=float(info.dual_res),
            objective=float(info.obj_val),
            setup_time_ms=1e3 * float(info.setup_time),
            solve_time_ms=1e3 * float(info.solve_time),
        )

    def _estimate(self, x: NDArray[np.float64], w: NDArray[np.float64], info: SolverInfo) -> Any:
        """Node displacements, contact pressures and forces from the QP's solution x."""
        ni = len(self.interior)
        u = np.zeros(self.n)
        u[self.interior] = self.length * x[:ni]
        pc = np.zeros(self.n)
        pc[self.interior] = np.minimum(x[ni : 2 * ni], 0.0) * self.pressure_scale
        contact_pressure = pc[:, None] * self.normals
        F = self.areas[:, None] * contact_pressure
        p = -pc
        seen = np.zeros(self.n, dtype=bool)
        seen[self._ray_nodes[w > 0].ravel()] = True
        return Estimate(
            node_forces=F,
            contact_pressure=contact_pressure,
            normal_pressure=p,
            contact=contact_mask(p, self.areas, self.k_const, self.k_linear),
            net_force=F[self.interior].sum(axis=0),
            displacements=u[:, None] * self.normals,
            info=info,
            valid_node_fraction=float(seen[self.interior].mean()) if ni else 1.0,
        )

    def process(self, frame: Any) -> Any:
        """Estimate from a ``Frame`` (uses ``frame.depth`` and ``frame.pressure_pa``)."""
        if frame.depth is None:
            raise ValueError("the frictionless baseline needs a depth image")
        return self.estimate_depth(frame.depth, frame.pressure_pa)


def _timing_main(argv: list[str] | None = None) -> int:
    """``python3 -m bubble_rt.estimation.baseline``: time per frame on a synthetic ray-cast sequence."""
    import argparse
    from types import SimpleNamespace

    from bubble_rt.camera import Camera
    from bubble_rt.mesh import Mesh
    from bubble_rt.reference import render_depth

    ap = argparse.ArgumentParser(description=_timing_main.__doc__)
    ap.add_argument("--mesh", default="medium", help="coarse | medium | fine")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--stride", type=int, default=FrictionlessSettings.pixel_stride)
    args = ap.parse_args(argv)
    mesh = Mesh.preset(args.mesh)
    cam = Camera.d405()
    V, T = mesh.vertices, mesh.triangles
    normals = vertex_normals(V, T)
    reference = SimpleNamespace(depth=render_depth(V, T, cam), pressure_pa=ATMOSPHERIC_PA + 3000)
    t0 = time.perf_counter()
    est = FrictionlessEstimator(
        mesh, cam, reference, settings=FrictionlessSettings(pixel_stride=args.stride)
    )
    setup_ms = 1e3 * (time.perf_counter() - t0)
    rng = np.random.default_rng(0)
    depths = []
    for k in range(args.frames):
        # A press that slides along x and releases, plus depth noise.
        amp = 4e-3 * np.sin(np.pi * (k + 0.5) / args.frames)
        cx = -0.02 + 0.04 * k / max(args.frames - 1, 1)
        c = np.exp(-((V[:, 0] - cx) ** 2 + V[:, 1] ** 2) / (2 * 0.008**2))
        c[mesh.boundary] = 0
        d = render_depth(V - amp * c[:, None] * normals, T, cam)
        d += (rng.standard_normal(d.shape) * 3e-4).astype(np.float32) * (d > 0)
        depths.append(d)
    total, solve, iters = [], [], []
    for d in depths:
        t = time.perf_counter()
        e = est.estimate_depth(d, reference.pressure_pa)
        total.append(1e3 * (time.perf_counter() - t))
        solve.append(e.timings_ms["solve"])
        iters.append(e.info.iterations)
    print(
        f"frictionless baseline, {args.mesh} ({mesh.n_nodes} nodes), 640x480, stride "
        f"{args.stride} ({est.n_rays} rays), {args.frames} frames: setup {setup_ms:.0f} ms, "
        f"per frame p50 {np.median(total):.2f} ms p99 {np.percentile(total, 99):.2f} ms, "
        f"solve p50 {np.median(solve):.2f} ms, iterations p50 {np.median(iters):.0f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(_timing_main())
