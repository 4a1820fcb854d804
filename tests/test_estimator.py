"""ForceEstimator: outputs consistent with the model, reconfigure, tracker plumbing."""

from __future__ import annotations

import dataclasses
import functools
from types import SimpleNamespace

import numpy as np
import pytest
from bubble_rt.estimation.estimator import Estimate, EstimatorConfig, ForceEstimator
from bubble_rt.estimation.membrane import Material
from bubble_rt.estimation.registry import make_estimator
from bubble_rt.estimation.solver import SolverSettings
from bubble_rt.mesh import Mesh


@functools.cache
def _mesh() -> Mesh:
    return Mesh.preset("coarse")


def _field(seed: int = 0, depth: float = 8e-3) -> tuple[np.ndarray, float]:
    mesh = _mesh()
    V = mesh.vertices
    r = np.linalg.norm(V[:, :2] - np.array([0.01, 0.005]), axis=1)
    U = np.zeros_like(V)
    U[:, 2] = -depth * np.exp(-((r / 0.015) ** 2))
    U[mesh.boundary] = 0.0
    U += np.random.default_rng(seed).normal(scale=2e-4, size=U.shape)
    return U, 40_000.0 * depth


def test_default_config_matches_paper():
    c = EstimatorConfig()
    assert (c.k_f, c.k_u, c.k_const, c.k_linear) == (0.3322, 537592.0, 2000.0, 2.0)
    assert c.material == Material(1.317e6, 0.5, 0.65e-3)
    assert c.solver == SolverSettings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.k_f = 1.0  # type: ignore[misc]


def test_estimate_outputs_are_consistent_with_the_model():
    est = ForceEstimator(_mesh())
    U, dp = _field()
    e = est.estimate(U, dp)
    n = _mesh().n_nodes
    assert isinstance(e, Estimate)
    assert e.node_forces.shape == e.contact_pressure.shape == e.displacements.shape == (n, 3)
    assert e.normal_pressure.shape == e.contact.shape == (n,)
    assert e.contact.dtype == bool
    assert e.info.status == "solved"
    assert np.all(e.displacements[_mesh().boundary] == 0.0)
    F = est.model.external_forces(e.displacements, dp)
    assert np.allclose(e.node_forces, F)
    assert np.allclose(e.contact_pressure, F / est.model.areas[:, None])
    assert np.allclose(e.normal_pressure, -(est.model.normals * e.contact_pressure).sum(axis=1))
    assert np.allclose(e.net_force, F[_mesh().interior].sum(axis=0))
    assert e.net_force[2] < 0 and e.contact.any()
    assert set(e.timings_ms) >= {"solve", "post"}
    assert e.valid_node_fraction == 1.0


def test_estimate_rejects_nan_and_keeps_state():
    a, b = ForceEstimator(_mesh()), ForceEstimator(_mesh())
    U, dp = _field()
    a.estimate(U, dp)
    b.estimate(U, dp)
    bad = U.copy()
    bad[4, 0] = np.nan
    with pytest.raises(ValueError, match="U has NaN or inf at node 4"):
        a.estimate(bad, dp)
    with pytest.raises(ValueError, match="dp"):
        a.estimate(U, float("inf"))
    U2, dp2 = _field(seed=1)
    assert np.array_equal(a.estimate(U2, dp2).node_forces, b.estimate(U2, dp2).node_forces)


def test_reconfigure_thresholds_only_changes_contact():
    est = ForceEstimator(_mesh())
    U, dp = _field()
    e0 = est.estimate(U, dp)
    est.reconfigure(k_const=1e9)
    e1 = est.estimate(U, dp)
    assert np.array_equal(e0.node_forces, e1.node_forces)
    assert e0.contact.any() and not e1.contact.any()
    assert est.config.k_const == 1e9


def test_reconfigure_weights_and_material():
    est = ForceEstimator(_mesh())
    U, dp = _field()
    e0 = est.estimate(U, dp)
    est.reconfigure(k_f=10 * 0.3322)
    e1 = est.estimate(U, dp)
    mesh = _mesh()
    w = np.where(mesh.interior, 1.0, len(mesh.boundary) / mesh.n_nodes)

    def l1(e: Estimate) -> float:
        return float(w @ np.linalg.norm(e.node_forces, axis=1))

    # Raising the weight of a term never raises that term at the optimum.
    assert l1(e1) < l1(e0)
    model = est.model
    est.reconfigure(material=Material(E=2.0e6))
    assert est.model is not model and est.model.material.E == 2.0e6
    e2 = est.estimate(U, dp)
    assert e2.info.status == "solved"
    with pytest.raises(ValueError):
        est.reconfigure(k_u=-1.0)
    with pytest.raises(TypeError):
        est.reconfigure(not_a_field=1.0)


def test_process_uses_attached_tracker_and_merges_timings():
    est = ForceEstimator(_mesh())
    U, dp = _field()
    tracker = SimpleNamespace(
        track=lambda frame: SimpleNamespace(
            U=U, dp=dp, valid_fraction=0.75, timings_ms={"flow": 1.0, "lift": 2.0}
        )
    )
    with pytest.raises(RuntimeError):
        est.process(object())
    est.attach(tracker)
    e = est.process(object())
    assert e.valid_node_fraction == 0.75
    assert {"flow", "lift", "solve", "post"} <= set(e.timings_ms)
    assert np.allclose(e.node_forces, est.estimate(U, dp).node_forces)


def test_make_estimator():
    assert isinstance(make_estimator("fem", _mesh()), ForceEstimator)
    with pytest.raises(ValueError, match="unknown estimator"):
        make_estimator("magic", _mesh())


def test_pressure_only_gives_uniform_inward_pressure_before_regularisation():
    # With dp only, the raw external force is -dp a n on every node; the group lasso then
    # shrinks it, but never flips its sign.
    est = ForceEstimator(_mesh())
    e = est.estimate(np.zeros((_mesh().n_nodes, 3)), 300.0)
    assert e.info.status == "solved"
    assert np.isfinite(e.normal_pressure).all()
    assert e.net_force[2] <= 1e-9
