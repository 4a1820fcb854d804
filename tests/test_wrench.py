"""The contact wrench and patch geometry (bubble_rt.wrench) and the daemon's frames of them."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.daemon.service import Daemon
from bubble_rt.io.client import Subscriber
from bubble_rt.mesh import Mesh
from bubble_rt.wrench import PatchFinder, net_torque
from daemon_fakes import FakeProcessor, ScriptedCamera, constant_pressure, fake_config

pytestmark = pytest.mark.timeout(60)

H = 0.002  # grid spacing of the flat patch, m


def flat_grid(n: int = 3) -> Mesh:
    """n x n nodes spaced H, centred on the origin, z = 0 (node k at column k % n, row
    k // n); every square split along its (+x, +y) diagonal, counter-clockwise seen from +z
    (outward normal +z)."""
    xs = (np.arange(n) - (n - 1) / 2) * H
    v = np.array([[x, y, 0.0] for y in xs for x in xs])
    t = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = n * j + i, n * j + i + 1, n * (j + 1) + i, n * (j + 1) + i + 1
            t += [[a, b, d], [a, d, c]]
    return Mesh(v, np.array(t, np.int32))


def test_patch_normal_peak_torque_and_centroids_on_a_flat_grid():
    mesh = flat_grid()
    pf = PatchFinder(mesh)
    x = mesh.vertices
    # Pressing harder towards +x: f_i = (0, 0, -(1 + x_i / H)) N.
    forces = np.zeros((9, 3))
    forces[:, 2] = -(1.0 + x[:, 0] / H)
    (p,) = pf.patches(np.ones(9, bool), forces)
    np.testing.assert_allclose(p.normal, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(p.force, [0, 0, -9.0])
    # Lumped areas are symmetric under a half turn, so the area centroid is the middle node.
    np.testing.assert_allclose(p.centroid, [0, 0, 0], atol=1e-15)
    # tau = sum x_i x f_i = (sum y_i f_z, -sum x_i f_z, 0) = (0, sum x_i^2 / H, 0) = (0, 6 H, 0)
    np.testing.assert_allclose(p.torque, [0, 6 * H, 0], atol=1e-15)
    # Load centre: sum x_i (1 + x_i / H) / 9 = 6 H / 9.
    np.testing.assert_allclose(p.pressure_centroid, [2 * H / 3, 0, 0], atol=1e-15)
    # Peak pressure: 2 N on the corner (H, -H), which only one triangle touches (H^2 / 6).
    assert p.peak_pressure == pytest.approx(2.0 / (H * H / 6))
    # A uniform displacement moves both centroids and leaves the torque about them alone.
    d = np.tile([0.001, -0.002, 0.003], (9, 1))
    (q,) = pf.patches(np.ones(9, bool), forces, displacements=d)
    np.testing.assert_allclose(q.centroid, d[0], atol=1e-15)
    np.testing.assert_allclose(q.pressure_centroid, [2 * H / 3 + 0.001, -0.002, 0.003])
    np.testing.assert_allclose(q.torque, p.torque, atol=1e-15)


def test_given_normal_pressure_sets_the_peak_and_a_tension_does_not_pull_the_load_centre():
    mesh = flat_grid()
    pf = PatchFinder(mesh)
    forces = np.zeros((9, 3))
    forces[:, 2] = -1.0
    pressure = np.full(9, 100.0)
    pressure[0] = -5000.0  # an outward pull: no contact load there
    pressure[8] = 700.0
    (p,) = pf.patches(np.ones(9, bool), forces, normal_pressure=pressure)
    assert p.peak_pressure == 700.0
    a = pf.areas
    w = np.clip(pressure, 0, None) * a
    np.testing.assert_allclose(p.pressure_centroid, (w / w.sum()) @ mesh.vertices)


def test_the_rule_pressure_weights_the_load_centre_and_the_reported_one_sets_the_peak():
    # The estimator reports the nonlinear refit's pressure (gathered at a dent's edge) and
    # places the load's centre with the linear refit's (Estimate.rule_pressure).
    from types import SimpleNamespace

    mesh = flat_grid()
    pf = PatchFinder(mesh)
    forces = np.zeros((9, 3))
    forces[:, 2] = -1.0
    reported = np.full(9, 100.0)
    reported[8] = 900.0  # the corner (H, H)
    rule = np.full(9, 100.0)
    rule[0] = 500.0  # the corner (-H, -H)
    e = SimpleNamespace(
        contact=np.ones(9, bool),
        node_forces=forces,
        displacements=None,
        normal_pressure=reported,
        support=None,
        rule_pressure=rule,
    )
    (p,) = pf.patches_of(e)
    assert p.peak_pressure == 900.0
    w = rule * pf.areas
    np.testing.assert_allclose(p.pressure_centroid, (w / w.sum()) @ mesh.vertices)
    assert p.pressure_centroid[0] < 0 and p.pressure_centroid[1] < 0
    # without a rule pressure (the frictionless baseline) the reported one weights it
    e.rule_pressure = np.zeros(0)
    (q,) = pf.patches_of(e)
    assert q.pressure_centroid[0] > 0 and q.pressure_centroid[1] > 0


def test_a_patch_carries_the_force_of_the_support_around_it():
    # 7 x 7 grid, one row y = 0: contact at columns 1 and 5, force on columns 0-6 of that row
    # (the estimator's support) plus a loaded node at a far corner, away from any contact.
    mesh = flat_grid(7)
    pf = PatchFinder(mesh)
    row = 3 * 7 + np.arange(7)
    contact = np.zeros(49, bool)
    contact[row[[1, 5]]] = True
    support = np.zeros(49, bool)
    support[row] = True
    support[0] = True
    forces = np.zeros((49, 3))
    forces[support, 2] = -1.0
    forces[row, 0] = np.arange(7) * 0.1  # a shear growing along +x
    left, right = sorted(pf.patches(contact, forces, support=support), key=lambda q: q.centroid[0])
    # Nearest contact node: columns 0-3 to the left patch (column 3 is a tie, taken by the
    # first patch), 4-6 to the right one; the far corner belongs to no patch.
    np.testing.assert_allclose(left.force, [0.0 + 0.1 + 0.2 + 0.3, 0, -4.0])
    np.testing.assert_allclose(right.force, [0.4 + 0.5 + 0.6, 0, -3.0])
    # Torque about the (single-node) centroid, over the nodes whose force the patch carries.
    c = mesh.vertices[row[1]]
    x = mesh.vertices[row[:4]]
    np.testing.assert_allclose(left.torque, np.cross(x - c, forces[row[:4]]).sum(axis=0))
    np.testing.assert_allclose(left.centroid, c)  # centroids stay on the contact nodes
    # Without a support a patch carries its contact nodes' forces only.
    q = sorted(pf.patches(contact, forces), key=lambda q: q.centroid[0])
    np.testing.assert_allclose(q[0].force, forces[row[1]])


def test_net_torque_skips_the_rim_and_non_finite_forces():
    mesh = Mesh.preset("coarse")
    rng = np.random.default_rng(3)
    f = rng.normal(size=(mesh.n_nodes, 3))
    tau = PatchFinder(mesh).net_torque(f)
    inner = mesh.interior
    np.testing.assert_allclose(tau, np.cross(mesh.vertices[inner], f[inner]).sum(axis=0))
    f_rim = f.copy()
    f_rim[mesh.boundary] = 1e3
    np.testing.assert_allclose(PatchFinder(mesh).net_torque(f_rim), tau)
    f[inner.nonzero()[0][0]] = np.nan
    assert np.isfinite(net_torque(mesh.vertices, f, inner)).all()


def test_net_torque_takes_the_forces_where_the_membrane_is():
    mesh = Mesh.preset("coarse")
    rng = np.random.default_rng(4)
    f = rng.normal(size=(mesh.n_nodes, 3))
    u = rng.normal(scale=2e-3, size=(mesh.n_nodes, 3))
    inner = mesh.interior
    x = mesh.vertices + u
    expected = np.cross(x[inner], f[inner]).sum(axis=0)
    np.testing.assert_allclose(PatchFinder(mesh).net_torque(f, u), expected)
    assert np.linalg.norm(PatchFinder(mesh).net_torque(f) - expected) > 1e-3
    u[inner.nonzero()[0][0]] = np.nan  # an unmeasured node counts at its vertex
    assert np.isfinite(net_torque(mesh.vertices, f, inner, u)).all()
    with pytest.raises(ValueError, match="displacements"):
        net_torque(mesh.vertices, f, inner, u[:-1])


class ShearingProcessor(FakeProcessor):
    """The fake's forces plus a shear on its nodes, a dent under them (which moves where the
    forces act) and a reaction on the rim (which the net torque must leave out)."""

    def stage2(self, frame, data):  # type: ignore[no-untyped-def]
        est = super().stage2(frame, data)
        est.node_forces[self.nodes, 0] = 0.3
        est.node_forces[self.nodes, 1] = -0.2 * np.arange(len(self.nodes))
        est.node_forces[self.mesh.boundary[:3]] = [0.05, 0.1, 0.2]
        est.displacements[self.nodes] = [0.0005, -0.001, -0.004]
        return est


def test_frame_torque_is_recomputed_from_the_frame_and_published_mesh_alone():
    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(),
        pressure=constant_pressure(),
        processor_factory=ShearingProcessor,
    ).start()
    try:
        assert d.wait_ready(20.0)
        with Subscriber(d.pub_address, d.control_address) as sub:
            mesh = sub.mesh
            frames = list(sub.frames(count=3, timeout_s=5))
    finally:
        d.stop()
    assert len(frames) == 3
    inner = np.ones(len(mesh.vertices), bool)
    inner[mesh.boundary] = False
    for f in frames:
        assert f.net_torque is not None and f.node_displacements is not None
        x = mesh.vertices + f.node_displacements  # where the forces act
        tau = np.cross(x[inner], f.node_forces[inner]).sum(axis=0)
        np.testing.assert_allclose(f.net_torque, tau, rtol=1e-12, atol=1e-15)
        all_nodes = np.cross(x, f.node_forces).sum(axis=0)
        assert np.linalg.norm(all_nodes - tau) > 1e-3 * np.linalg.norm(tau)  # the rim matters
        undented = np.cross(mesh.vertices[inner], f.node_forces[inner]).sum(axis=0)
        assert np.linalg.norm(undented - tau) > 1e-2 * np.linalg.norm(tau)  # so does the dent
        (p,) = f.patches
        assert p.normal.shape == (3,) and np.linalg.norm(p.normal) == pytest.approx(1.0)
        assert p.peak_pressure == 5000.0  # the fake's contact pressure
        assert p.torque.shape == (3,) and p.pressure_centroid.shape == (3,)


def test_contact_nodes_of_one_load_region_are_one_patch():
    mesh = Mesh.preset("coarse")
    pf = PatchFinder(mesh)
    inner = np.flatnonzero(mesh.interior)
    a, b = inner[0], inner[-1]  # far apart: two components without labels
    contact = np.zeros(mesh.n_nodes, bool)
    contact[[a, b]] = True
    forces = np.zeros((mesh.n_nodes, 3))
    forces[[a, b], 2] = -1.0
    assert len(pf.patches(contact, forces)) == 2
    label = np.full(mesh.n_nodes, -1)
    label[[a, b]] = 7
    (p,) = pf.patches(contact, forces, label=label)
    assert sorted(p.nodes.tolist()) == sorted([a, b])
    np.testing.assert_allclose(p.force, [0.0, 0.0, -2.0])
