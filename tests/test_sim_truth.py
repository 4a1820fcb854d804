"""Ground truth: displacement map and contact transfer to estimator meshes."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.mesh import Mesh
from bubble_rt.sim.truth import GroundTruth, SurfaceLocator, closest_points_on_triangles


def truth_for(sim: Mesh, current: np.ndarray, contact: np.ndarray) -> GroundTruth:
    n = len(sim.vertices)
    return GroundTruth(
        indenter_pose=np.eye(4),
        net_force=np.zeros(3),
        node_forces=np.zeros((n, 3)),
        pressure_pa=106325.0,
        sim_vertices=current,
        sim_reference_vertices=sim.vertices,
        sim_triangles=sim.triangles,
        contact=contact,
    )


def test_displace_is_identity_at_reference():
    sim = Mesh.generate(1200)
    gt = truth_for(sim, sim.vertices, np.zeros(sim.n_nodes, bool))
    est = Mesh.preset("medium")  # its own dome: nodes a little off the sim surface
    np.testing.assert_allclose(gt.displace(est.vertices), est.vertices, atol=1e-15)
    np.testing.assert_allclose(gt.displace(sim.vertices), sim.vertices, atol=1e-15)


def test_displace_reproduces_an_affine_motion_of_surface_points():
    sim = Mesh.generate(800)
    A = np.array([[1.01, 0.02, 0.0], [-0.01, 0.99, 0.03], [0.0, 0.01, 0.97]])
    b = np.array([0.001, -0.002, 0.0005])
    gt = truth_for(sim, sim.vertices @ A.T + b, np.zeros(sim.n_nodes, bool))
    rng = np.random.default_rng(1)
    tri = rng.integers(0, sim.n_triangles, 300)
    lam = rng.dirichlet(np.ones(3), 300)
    pts = np.einsum("ij,ijk->ik", lam, sim.vertices[sim.triangles[tri]])
    np.testing.assert_allclose(gt.displace(pts), pts @ A.T + b, atol=1e-12)


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(2)
    a, b, c = (rng.normal(size=(500, 3)) for _ in range(3))
    p = rng.normal(size=(500, 3)) * 2
    lam = closest_points_on_triangles(p, a, b, c)
    q = lam[:, :1] * a + lam[:, 1:2] * b + lam[:, 2:] * c
    assert (lam >= -1e-12).all() and np.allclose(lam.sum(axis=1), 1)
    d_best = np.linalg.norm(q - p, axis=1)
    g = np.linspace(0, 1, 61)
    U, W = np.meshgrid(g, g)
    keep = (U + W) <= 1
    L = np.column_stack([1 - U[keep] - W[keep], U[keep], W[keep]])
    for i in range(0, 500, 50):
        samples = L @ np.stack([a[i], b[i], c[i]])
        assert d_best[i] <= np.linalg.norm(samples - p[i], axis=1).min() + 1e-12


def test_locator_finds_the_triangle_under_a_point():
    sim = Mesh.generate(600)
    loc = SurfaceLocator(sim.vertices, sim.triangles)
    tri, lam = loc.locate(sim.vertices[sim.triangles[37]].mean(axis=0, keepdims=True))
    assert tri[0] == 37
    np.testing.assert_allclose(lam[0], [1 / 3] * 3, atol=1e-9)


def test_contact_mask_transfers_a_known_contact_disc():
    sim = Mesh.generate(2500)
    R = 0.015
    r_sim = np.hypot(sim.vertices[:, 0], sim.vertices[:, 1])
    gt = truth_for(sim, sim.vertices, r_sim < R)
    est = Mesh.preset("medium")
    mask = gt.contact_mask(est)
    r_est = np.hypot(est.vertices[:, 0], est.vertices[:, 1])
    h = est.edge_lengths().max()  # a node's region reaches at most about an edge away
    assert mask[r_est < R - h].all()
    assert not mask[r_est > R + h].any()
    # The masked lumped area is the disc's area (on the dome) within a ring of one edge.
    from bubble_rt.sim.truth import _lattice_samples

    assert len(_lattice_samples()) % 3 == 0
    n_inside = mask.sum()
    assert np.sum(r_est < R - h) <= n_inside <= np.sum(r_est < R + h)


def test_contact_mask_marks_the_node_under_a_pin_smaller_than_a_node():
    """A loaded contact on one simulation node covers no estimator node's region by half, but
    the truth still marks one node: the one nearest the pin, the only one that can carry it."""
    from dataclasses import replace

    from bubble_rt.sim.truth import TOUCH_N

    sim = Mesh.generate(2500)
    est = Mesh.preset("medium")
    target = est.vertices[np.argmin(np.hypot(est.vertices[:, 0] - 0.006, est.vertices[:, 1]))]
    # the pin's simulation node: the one nearest a point a third of an edge beside the target
    h = est.edge_lengths().mean()
    j = int(np.argmin(np.linalg.norm(sim.vertices - (target + [h / 3, 0, 0]), axis=1)))
    contact = np.zeros(sim.n_nodes, bool)
    contact[j] = True
    forces = np.zeros((sim.n_nodes, 3))
    forces[j] = [0.0, 0.0, -1.0]  # 1 N on the pin
    gt = replace(truth_for(sim, sim.vertices, contact), node_forces=forces)
    mask = gt.contact_mask(est)
    nearest = int(np.argmin(np.linalg.norm(est.vertices - sim.vertices[j], axis=1)))
    assert np.flatnonzero(mask).tolist() == [nearest]
    # the same pin below a touch's force is no contact, as with no pin at all
    light = replace(gt, node_forces=forces * 0.5 * TOUCH_N)
    assert not light.contact_mask(est).any()
    # without the load the region alone marks no node: the pin is below half a node's region
    assert not truth_for(sim, sim.vertices, contact).contact_mask(est).any()


def test_contact_mask_of_no_contact_is_empty():
    sim = Mesh.generate(500)
    gt = truth_for(sim, sim.vertices, np.zeros(sim.n_nodes, bool))
    assert not gt.contact_mask(Mesh.preset("coarse")).any()


def test_contact_mask_of_full_contact_covers_every_node():
    sim = Mesh.generate(500)
    gt = truth_for(sim, sim.vertices, np.ones(sim.n_nodes, bool))
    assert gt.contact_mask(Mesh.preset("coarse")).all()


def test_true_torque_and_patches_from_the_contact_forces():
    sim = Mesh.generate(400)
    n = sim.n_nodes
    inner = np.flatnonzero(sim.interior)
    x = sim.vertices
    # Two loaded groups: the 3 interior nodes nearest x = -10 mm and nearest x = +10 mm.
    left = inner[np.argsort(np.abs(x[inner, 0] + 0.01) + np.abs(x[inner, 1]))[:1]]
    right = inner[np.argsort(np.abs(x[inner, 0] - 0.01) + np.abs(x[inner, 1]))[:1]]
    f = np.zeros((n, 3))
    f[left] = [0.0, 0.0, -1.0]
    f[right] = [0.2, 0.0, -3.0]
    f[sim.boundary[0]] = [0.0, 0.0, 5.0]  # on the rim: left out of the net force and torque
    contact = np.zeros(n, bool)
    contact[np.concatenate([left, right])] = True
    interior = sim.interior
    gt = GroundTruth(
        indenter_pose=np.eye(4),
        net_force=f[interior].sum(axis=0),
        node_forces=f,
        pressure_pa=106325.0,
        sim_vertices=x,
        sim_reference_vertices=x,
        sim_triangles=sim.triangles,
        contact=contact,
        interior=interior,
    )
    expected = np.cross(x[left[0]], f[left[0]]) + np.cross(x[right[0]], f[right[0]])
    np.testing.assert_allclose(gt.net_torque(), expected)
    big, small = gt.patches()
    np.testing.assert_allclose(big.force, [0.2, 0, -3.0])
    np.testing.assert_allclose(big.centroid, x[right[0]])
    np.testing.assert_allclose(small.centroid, x[left[0]])
    # each patch's area: its nodes' lumped areas on the untouched surface
    areas = sim.lumped_areas()
    assert big.area == pytest.approx(areas[right].sum())
    assert small.area == pytest.approx(areas[left].sum())
