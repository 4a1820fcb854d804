"""Issue 12: estimator variants measured on the same tracked frames (docs/evaluation.md, "What
each accuracy step buys").

Tracks the frames of `bubble-rt eval` once per trajectory (same simulation, reference capture,
mesh fit and DeformationTracker as `evaluate_trajectory`), then runs every variant on the same
(U, dp) and scores it with `bubble_rt.eval.metrics.frame_metrics` / `summarize`. The variants
that lost are prototyped here only (NumPy); the product runs the winner (`ForceEstimator` defaults).
"ms": median per frame of the estimate from (U, dp) (not flow / lifting), frames after the
first of each trajectory; the baseline's is its whole process(frame) from images.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/accuracy_variants.py --quick
    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/accuracy_variants.py --seed 1000 \\
        --trajectories 4 --frames 20      # the calibration seeds the choices were made on
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import scipy.sparse as sp
from bubble_rt import eval as ev
from bubble_rt.estimation.deformation import DeformationTracker, FlowSettings, Reference
from bubble_rt.estimation.estimator import EstimatorConfig, ForceEstimator
from bubble_rt.estimation.membrane import (
    Material,
    MembraneModel,
    _triangle_gradients,
    coordinatewise_stiffness,
    inflation_stiffness,
)
from bubble_rt.estimation.solver import GroupLassoSolver
from bubble_rt.mesh import Mesh

PAPER_E, PAPER_KF, KU = 1.317e6, 0.3322, 537592.0


def track(seed: int, trajectories: int, frames: int) -> list[dict[str, Any]]:
    data = []
    for g in ev.GEOMETRIES:
        for k in range(trajectories):
            traj = ev.simulate_trajectory(g, k, frames, seed)
            mesh = ev.estimator_mesh("medium", traj)
            ref = Reference.capture(traj.reference_frames)
            tracker = DeformationTracker(mesh, traj.camera, ref, FlowSettings())
            base = ev.build_estimator("frictionless", mesh, traj, EstimatorConfig())
            rec: dict[str, Any] = {"geometry": g, "traj": k, "mesh": mesh, "ref": ref, "frames": []}
            for fr in traj.frames:
                d = tracker.track(fr)
                t0 = time.perf_counter()
                b = base.process(fr)
                rec["frames"].append(
                    {
                        "U": np.array(d.U),
                        "dp": d.dp,
                        "f_gt": np.asarray(fr.truth.net_force, float),
                        "gt": np.asarray(fr.truth.contact_mask(mesh), bool),
                        "conv": bool(getattr(fr.truth, "converged", True)),
                        "base": (np.asarray(b.net_force), np.asarray(b.contact, bool)),
                        "base_ms": 1e3 * (time.perf_counter() - t0),
                    }
                )
            data.append(rec)
    return data


def anisotropic_geometric(mesh: Mesh, p0: float, reg: float = 1e-3) -> sp.csr_matrix:
    """Variant H: per-triangle prestress fitted to p0 (least squares + Tikhonov to uniform)."""
    from bubble_rt.estimation.membrane import inflation_tension

    V, T = mesh.vertices, mesh.triangles
    area, frame, G = _triangle_gradients(V, T)
    nt, n = len(T), len(V)
    rows, cols, vals = [], [], []
    for a in range(3):
        for ci, pairs in enumerate((((0, 0),), ((1, 1),), ((0, 1), (1, 0)))):
            vec = sum(G[:, al, a, None] * frame[:, be] for al, be in pairs) * area[:, None]
            for d in range(3):
                rows.append(3 * T[:, a] + d)
                cols.append(3 * np.arange(nt) + ci)
                vals.append(vec[:, d])
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))))
    B = sp.csr_matrix(B, shape=(3 * n, 3 * nt))
    idof = (3 * np.flatnonzero(mesh.interior)[:, None] + np.arange(3)).ravel()
    normal = np.cross(frame[:, 0], frame[:, 1])
    an = np.zeros_like(V)
    for a in range(3):
        np.add.at(an, T[:, a], area[:, None] * normal / 3.0)
    B, rhs = B[idof], p0 * an.ravel()[idof]
    t0 = inflation_tension(mesh, p0)
    BtB = (B.T @ B).tocsc()
    lam = reg * BtB.diagonal().mean()
    s = sp.linalg.spsolve(
        BtB + lam * sp.identity(3 * nt, format="csc"), B.T @ rhs + lam * np.tile([t0, t0, 0.0], nt)
    )
    S = np.zeros((nt, 2, 2))
    s = s.reshape(nt, 3)
    S[:, 0, 0], S[:, 1, 1], S[:, 0, 1], S[:, 1, 0] = s[:, 0], s[:, 1], s[:, 2], s[:, 2]
    L = area[:, None, None] * np.einsum("tka,tkl,tlb->tab", G, S, G)
    return coordinatewise_stiffness(T, L, n)


def model_for(mesh: Mesh, E: float, p0: float, kind: str) -> MembraneModel:
    """kind: "material" (paper), "inflated" (product), "geometric" (no load term), "aniso"."""
    if kind == "inflated":
        return MembraneModel(mesh, Material(E=E), p0)
    m = MembraneModel(mesh, Material(E=E))
    if kind in ("geometric", "aniso"):
        full, t0 = inflation_stiffness(mesh, p0)  # T0 x Laplacian - K_load
        geo = _geometric_only(mesh, t0)
        dK = geo if kind == "geometric" else anisotropic_geometric(mesh, p0) + (full - geo)
        m._core.add_stiffness(sp.csc_matrix(dK))
        m.__dict__.pop("stiffness", None)
    return m


def _geometric_only(mesh: Mesh, tension: float) -> sp.csr_matrix:
    V, T = mesh.vertices, mesh.triangles
    area, _, G = _triangle_gradients(V, T)
    L = (area * tension)[:, None, None] * np.einsum("tka,tkb->tab", G, G)
    return coordinatewise_stiffness(T, L, len(V))


class Refit:
    """NumPy twin of cpp/support_refit (dense H = (K_ff K_ff^T)^-1)."""

    def __init__(self, model: MembraneModel, mesh: Mesh) -> None:
        self.free = np.flatnonzero(mesh.interior)
        self.fd = (3 * self.free[:, None] + np.arange(3)).ravel()
        self.K = model.stiffness.tocsr()
        self.G = np.linalg.inv(self.K[self.fd][:, self.fd].toarray())
        self.H = self.G.T @ self.G
        self.model, self.mesh = model, mesh

    def __call__(self, U: np.ndarray, dp: float, support: np.ndarray) -> np.ndarray:
        U0 = U.copy()
        U0[self.mesh.boundary] = 0.0
        fr = (self.K @ U0.ravel() - dp * self.model.area_normals.ravel())[self.fd]
        sl = np.flatnonzero(support[self.free])
        sd = (3 * sl[:, None] + np.arange(3)).ravel()
        f = np.zeros(len(self.fd))
        if len(sd):
            f[sd] = np.linalg.solve(self.H[np.ix_(sd, sd)], self.H[sd] @ fr)
        V = U0.ravel().copy()
        V[self.fd] += self.G @ (f - fr)
        return V.reshape(-1, 3)


VARIANTS: list[tuple[str, dict[str, Any]]] = [
    ("A paper: material K, group lasso, paper contact (before)", {}),
    ("B A + the public code's weighting k_u/(N/|dM|)^2", {"code_weights": True}),
    ("C A + refit on the lasso's support", {"refit": True}),
    ("D inflated K (material + geometric + load), group lasso", {"K": "inflated"}),
    ("E D + support/peak contact rule", {"K": "inflated", "contact": "support"}),
    ("F E + k_f 0.1 + refit", {"K": "inflated", "contact": "support", "k_f": 0.1, "refit": True}),
    (
        "G F without the load stiffness, E 0.66 MPa",
        {"K": "geometric", "contact": "support", "k_f": 0.1, "refit": True, "E": 0.66e6},
    ),
    (
        "H F with a fitted anisotropic prestress, E 0.66 MPa",
        {"K": "aniso", "contact": "support", "k_f": 0.1, "refit": True, "E": 0.66e6},
    ),
    (
        "I inflated K, E 0.66 MPa, no lasso (raw F = K U - dp a n)",
        {"K": "inflated", "raw": True, "E": 0.66e6},
    ),
    (
        "J the default's linear refit (nonlinear_iterations 0), E 0.55 MPa: the default "
        "until issue 20",
        {"product": {"nonlinear_iterations": 0, "material": Material(0.55e6, 0.5, 0.65e-3)}},
    ),
    (
        f"default: F with E {EstimatorConfig().material.E / 1e6:.2f} MPa and the nonlinear refit, k_f "
        f"{EstimatorConfig().k_f} (ForceEstimator, C++)",
        {"product": True},
    ),
]


def run(data: list[dict[str, Any]], v: dict[str, Any]) -> list[ev.FrameMetrics]:
    recs = []
    for tr in data:
        mesh: Mesh = tr["mesh"]
        p0 = EstimatorConfig().gauge_pressure(tr["ref"].pressure_pa)
        areas = ev.lumped_areas(mesh.vertices, mesh.triangles)
        normals = ev.vertex_normals(mesh.vertices, mesh.triangles)
        inter = mesh.interior
        kf = v.get("k_f", PAPER_KF)
        ku = KU * (len(mesh.boundary) ** 2 / mesh.n_nodes if v.get("code_weights") else 1.0)
        if v.get("product"):
            changes = v["product"] if isinstance(v["product"], dict) else {}
            prod = ForceEstimator(
                mesh,
                EstimatorConfig(**changes),
                SimpleNamespace(pressure_pa=tr["ref"].pressure_pa),
            )
        else:
            model = model_for(mesh, v.get("E", PAPER_E), p0, v.get("K", "material"))
            solver = GroupLassoSolver(model, kf, ku)
            refit = Refit(model, mesh) if v.get("refit") else None
        for i, fr in enumerate(tr["frames"]):
            U, dp = fr["U"], fr["dp"]
            t0 = time.perf_counter()
            if v.get("product"):
                e = prod.estimate(U, dp)
                f, c = e.net_force, e.contact
            else:
                if v.get("raw"):
                    V = U.copy()
                    V[mesh.boundary] = 0.0
                    sup = inter
                else:
                    res = solver.solve_frame(U, dp)
                    V = U + res.dU
                    V[mesh.boundary] = 0.0
                    sup = inter & (np.linalg.norm(res.dual, axis=1) >= (1 - 1e-3) * kf)
                    if refit is not None:
                        V = refit(U, dp, sup)
                F = model.external_forces(V, dp)
                p = model.normal_pressure(F)
                c = model.contact_mask(p, 2000.0, 2.0)
                if v.get("contact") == "support":
                    c &= sup
                    if c.any():
                        c &= p >= 0.5 * p[sup].max()
                f = model.net_force(F)
            ms = 1e3 * (time.perf_counter() - t0)
            kw = dict(
                geometry=tr["geometry"],
                trajectory=tr["traj"],
                frame=i,
                f_gt=fr["f_gt"],
                gt_contact=fr["gt"],
                normals=normals,
                areas=areas,
                interior=inter,
                truth_converged=fr["conv"],
            )
            recs.append(ev.frame_metrics(estimator="v", f_est=f, est_contact=c, time_ms=ms, **kw))
            recs.append(
                ev.frame_metrics(
                    estimator="b",
                    f_est=fr["base"][0],
                    est_contact=fr["base"][1],
                    time_ms=fr["base_ms"],
                    **kw,
                )
            )
    return recs


def ratios(recs: list[ev.FrameMetrics], est: str) -> tuple[float, float]:
    light, firm = [], []
    for r in recs:
        if r.estimator == est and r.truth_converged and r.gt_contact:
            g = float(np.linalg.norm(r.f_gt))
            (firm if g >= 1.0 else light if g >= 0.3 else []).append(
                float(np.linalg.norm(r.f_est)) / g
            )
    return float(np.median(light)), float(np.median(firm))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 trajectories x 8 frames (eval --quick)")
    ap.add_argument("--seed", type=int, default=ev.EVAL_SEED_BASE)
    ap.add_argument("--trajectories", type=int, default=4)
    ap.add_argument("--frames", type=int, default=20)
    a = ap.parse_args()
    n_t, n_f = (2, 8) if a.quick else (a.trajectories, a.frames)
    data = track(a.seed, n_t, n_f)
    print(
        "| variant | force err (N) | per indenter (round / point / line / square / split) "
        "| ratio light / firm | mIoU | light det. | false contact | ms (median) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for k, (name, v) in enumerate(VARIANTS):
        recs = run(data, v)
        s = ev.summarize(recs)
        rows = [("v", name)] + ([("b", "frictionless baseline (Kuppuswamy)")] if k == 0 else [])
        for est, label in rows:
            av = s["average"][est]
            per = " / ".join(
                f"{s['geometries'][g][est]['force_err_n']:.2f}" for g in s["geometries"]
            )
            lr, fr = ratios(recs, est)
            ms = float(np.median([r.time_ms for r in recs if r.estimator == est and r.frame > 0]))
            print(
                f"| {label} | {av['force_err_n']:.2f} | {per} | {lr:.2f} / {fr:.2f} | {av['miou']:.3f} | {av['light_touch_rate']:.2f} | {av['false_contact_rate']:.2f} | {ms:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
