"""Issue 20: where the net torque's and the split pins' errors come from (docs/evaluation.md,
"Diagnosis of the torque and split errors").

Runs the fem estimator on the trajectories of `bubble-rt eval` twice, with image tracking (the
product) and with the simulator's true displacements (``--flow oracle``), and prints, over the
frames whose true net force is at least 1 N (medians):

- torque: ``|tau - tau_gt| / |tau_gt|`` about the mesh origin (truth at its untouched
  positions, the published definition), split into the net force's error at the truth's
  force-weighted centre ``|c_gt x (F - F_gt)|`` and the rest (the force distribution's moment
  about ``c_gt``), both over ``|tau_gt|``; the moment of each side about its own centre (mNm);
- net force read along the truth's contact normal and along its shear direction (estimate /
  truth, frames whose true shear is at least 0.3 N), and the same of the unregularised model
  ``K U - dp a n`` on the true displacements at the estimator's nodes (``raw_true_u_*``: the
  model's own read, without tracking or regularisation) and of its geometrically nonlinear
  form (``raw_true_u_nl_*``: ``GreenMembrane``, the forces the estimator reports);
- split frames with two true pins of at least 0.5 N: every interior node's force given to the
  nearest true pin, the worse pin's ``|F - F_gt| / |F_gt|`` and the part of it across F_gt.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/wrench_diagnosis.py            # default seeds
    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/wrench_diagnosis.py --seed 4242
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from bubble_rt import eval as ev
from bubble_rt.estimation.estimator import EstimatorConfig
from bubble_rt.eval.metrics import WRENCH_MIN_N
from bubble_rt.mesh import vertex_normals
from scipy.spatial import cKDTree

METHODS = ("default", "oracle")


def _centre(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    w = np.linalg.norm(f, axis=1)
    return np.asarray((w[:, None] * x).sum(axis=0) / w.sum())


def frame_terms(e: Any, truth: Any, mesh: Any, model: Any) -> dict[str, float]:
    """The diagnosis' quantities of one frame (module docstring); ``model`` the estimator's
    MembraneModel."""
    it = np.asarray(mesh.interior, dtype=bool)
    V = np.asarray(mesh.vertices)[it]
    F = np.asarray(e.node_forces, dtype=float)[it]
    keep = truth._interior()
    X = np.asarray(truth.sim_reference_vertices)[keep]
    G = np.asarray(truth.node_forces, dtype=float)[keep]
    te, tg = np.cross(V, F).sum(axis=0), np.cross(X, G).sum(axis=0)
    Fe, Fg = F.sum(axis=0), G.sum(axis=0)
    ce, cg = _centre(V, F), _centre(X, G)
    n = float(np.linalg.norm(tg))
    net = np.cross(cg, Fe - Fg)
    out = {
        "torque": float(np.linalg.norm(te - tg)) / n,
        "net_force_term": float(np.linalg.norm(net)) / n,
        "distribution_term": float(np.linalg.norm(te - tg - net)) / n,
        "own_moment_mNm": 1e3 * float(np.linalg.norm(te - np.cross(ce, Fe))),
        "true_own_moment_mNm": 1e3 * float(np.linalg.norm(tg - np.cross(cg, Fg))),
    }
    normals = vertex_normals(
        np.asarray(truth.sim_reference_vertices), np.asarray(truth.sim_triangles)
    )[keep]
    nc = -(np.linalg.norm(G, axis=1)[:, None] * normals).sum(axis=0)
    nc /= np.linalg.norm(nc)
    shear_gt = Fg - (Fg @ nc) * nc
    # The unregularised model K U - dp a n on the true displacements at the estimator's nodes.
    V_all = np.asarray(mesh.vertices)
    U_true = truth.displace(V_all) - V_all
    U_true[~it] = 0.0
    Fr = model.external_forces(U_true, e.pressure_delta_pa)[it].sum(axis=0)
    Fn = model.nonlinear.external_forces(U_true, e.pressure_delta_pa)[it].sum(axis=0)
    out["normal_read"] = float((Fe @ nc) / (Fg @ nc))
    out["raw_true_u_normal_read"] = float((Fr @ nc) / (Fg @ nc))
    out["raw_true_u_nl_normal_read"] = float((Fn @ nc) / (Fg @ nc))
    if np.linalg.norm(shear_gt) >= 0.3:
        u = shear_gt / np.linalg.norm(shear_gt)
        out["shear_read"] = float((Fe @ u) / np.linalg.norm(shear_gt))
        out["raw_true_u_shear_read"] = float((Fr @ u) / np.linalg.norm(shear_gt))
        out["raw_true_u_nl_shear_read"] = float((Fn @ u) / np.linalg.norm(shear_gt))
    pins = [p for p in truth.patches() if np.linalg.norm(p.force) >= 0.5]
    if len(pins) == 2:
        Xall = np.asarray(truth.sim_reference_vertices)
        d = np.stack([cKDTree(Xall[p.nodes]).query(V)[0] for p in pins], axis=1)
        own = np.argmin(d, axis=1)
        worst = (0.0, 0.0)
        for k, p in enumerate(pins):
            err = F[own == k].sum(axis=0) - p.force
            m = float(np.linalg.norm(p.force))
            u = p.force / m
            rel = float(np.linalg.norm(err)) / m
            if rel > worst[0]:
                worst = (rel, float(np.linalg.norm(err - (err @ u) * u)) / m)
        out["split_worse_pin"], out["split_across"] = worst
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=ev.EVAL_SEED_BASE)
    ap.add_argument("--trajectories", type=int, default=4)
    ap.add_argument("--frames", type=int, default=20)
    a = ap.parse_args()
    rows: dict[str, list[dict[str, float]]] = {m: [] for m in METHODS}
    for g in ev.GEOMETRIES:
        for k in range(a.trajectories):
            for method in METHODS:
                traj = ev.simulate_trajectory(g, k, a.frames, a.seed, render=method != "oracle")
                mesh = ev.estimator_mesh("medium", traj)
                est = ev.build_estimator("fem", mesh, traj, EstimatorConfig(), method)
                for frame in traj.frames:
                    e = est.process(frame)
                    t = frame.truth
                    if t.converged and np.linalg.norm(t.net_force) >= WRENCH_MIN_N:
                        rows[method].append(frame_terms(e, t, mesh, est.estimator.model))
    keys = list(dict.fromkeys(k for v in rows.values() for r in v for k in r))
    print(f"seed {a.seed}: medians over frames >= {WRENCH_MIN_N:g} N")
    print("| tracking | frames | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 2) + "|")
    for method, v in rows.items():
        med = [np.nanmedian([r.get(k, np.nan) for r in v]) for k in keys]
        print(f"| {method} | {len(v)} | " + " | ".join(f"{x:.3f}" for x in med) + " |")


if __name__ == "__main__":
    main()
