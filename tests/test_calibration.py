"""Calibration loss and optimiser on a tiny synthetic problem with a stand-in estimator."""

from __future__ import annotations

import math
import tomllib
from types import SimpleNamespace

import numpy as np
import pytest
from bubble_rt.eval import FanOut, load_config_overrides, lumped_areas, vertex_normals
from bubble_rt.eval.calibration import (
    DEFAULTS,
    CalibFrame,
    CalibrationProblem,
    calibrate,
    contact_threshold,
    frame_loss,
    write_config,
)
from bubble_rt.mesh import Mesh


class SpringStandIn:
    """Stand-in for ForceEstimator: node force = (E / E0) * s * U, pressure shrunk by k_f."""

    S = 200.0  # N/m per node at the default E

    def __init__(self, mesh, params):
        self.mesh = mesh
        self.a = lumped_areas(mesh.vertices, mesh.triangles)
        self.n = vertex_normals(mesh.vertices, mesh.triangles)
        self.interior = np.ones(mesh.n_nodes, bool)
        self.interior[mesh.boundary] = False
        self.E = params["E"]
        self.reconfigure(k_f=params["k_f"], k_u=params["k_u"])

    def reconfigure(self, k_f, k_u):
        self.k_f, self.k_u = k_f, k_u

    def estimate(self, U, dp):
        F = (self.E / DEFAULTS["E"]) * self.S * np.asarray(U)
        p = -(self.n * F).sum(axis=1) / self.a
        # L1-like shrinkage of the pressure; k_u lightly smooths the magnitude.
        shrink = 3000.0 * self.k_f / DEFAULTS["k_f"] * (DEFAULTS["k_u"] / self.k_u) ** 0.1
        p = np.sign(p) * np.maximum(np.abs(p) - shrink, 0.0)
        return SimpleNamespace(net_force=F[self.interior].sum(axis=0), normal_pressure=p)


def _problem(n_frames: int = 6) -> CalibrationProblem:
    mesh = Mesh.preset("coarse")
    truth = SpringStandIn(mesh, {"E": 2.0 * DEFAULTS["E"], "k_f": 0.05, "k_u": DEFAULTS["k_u"]})
    rng = np.random.default_rng(0)
    n = vertex_normals(mesh.vertices, mesh.triangles)
    frames = []
    for k in range(n_frames):
        centre = mesh.vertices[rng.integers(mesh.n_nodes)]
        d = np.linalg.norm(mesh.vertices - centre, axis=1)
        depth = 0.002 * (1 + k % 3) * np.clip(1 - d / 0.012, 0, None)
        U = -depth[:, None] * n
        U[mesh.boundary] = 0.0
        t = truth.estimate(U, 0.0)
        thr = contact_threshold(t.normal_pressure, truth.a, 2000.0, 2.0)
        frames.append(CalibFrame(U, 0.0, t.net_force, t.normal_pressure > thr))
    return CalibrationProblem(mesh, frames, factory=SpringStandIn)


def test_frame_loss_hand_value():
    a = np.ones(4)
    p = np.zeros(4)
    loss = frame_loss(np.array([3.0, 4.0, 0.0]), p, a, np.zeros(3), np.zeros(4, bool))
    sig = 1 / (1 + math.exp(2.0))  # sigmoid(2 * (0 - 2000) / 2000)
    assert loss == pytest.approx(5.0 + 10.0 * sig)


def test_frame_loss_threshold_follows_mean_pressure():
    a = np.ones(4)
    p = np.array([10000.0, 10000.0, 10000.0, 10000.0])
    # threshold = max(2000, 2 * 10000) = 20000, every node sits at sigmoid(-1)
    loss = frame_loss(np.zeros(3), p, a, np.zeros(3), np.zeros(4, bool))
    assert loss == pytest.approx(10.0 / (1 + math.exp(1.0)))


def test_loss_same_inline_and_in_processes():
    prob = _problem()
    inline = prob.loss(DEFAULTS)
    with FanOut(workers=2) as fan:
        parallel = prob.loss(DEFAULTS, fan)
    assert parallel == pytest.approx(inline, rel=1e-12)


def test_calibration_improves_on_defaults(tmp_path):
    prob = _problem()
    res = calibrate(prob, max_evals=40)
    assert res.initial_loss == pytest.approx(prob.loss(DEFAULTS))
    assert res.loss < 0.5 * res.initial_loss
    # the stand-in's stiffness is recovered roughly (truth: twice the default E)
    assert 1.3 < res.params["E"] / DEFAULTS["E"] < 3.0
    out = tmp_path / "calib.toml"
    write_config(out, res)
    doc = tomllib.loads(out.read_text())
    assert doc["estimator"]["youngs_modulus"] == pytest.approx(res.params["E"])
    assert set(doc) == {"estimator"}
    assert load_config_overrides(out) == pytest.approx(res.params)


def test_calibration_powell_improves():
    prob = _problem(4)
    res = calibrate(prob, method="Powell", max_evals=30)
    assert res.loss < res.initial_loss
    assert res.evaluations <= 31


def test_loss_same_on_dask_local_cluster_as_processes():
    distributed = pytest.importorskip("distributed")
    prob = _problem(4)
    with FanOut(workers=2) as fan:
        expected = prob.loss(DEFAULTS, fan)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        with FanOut(scheduler=cluster.scheduler_address) as fan:
            assert fan.parallelism == 2
            got = prob.loss(DEFAULTS, fan)
    assert got == pytest.approx(expected, rel=1e-12)
