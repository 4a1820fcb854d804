"""Tests of the frictionless baseline (bubble_rt.estimation.baseline) on ray-cast synthetic depth."""

from __future__ import annotations

from dataclasses import replace
from functools import cache
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from bubble_rt import reference as ref
from bubble_rt.camera import Camera
from bubble_rt.estimation.baseline import (
    FrictionlessEstimator,
    FrictionlessSettings,
    cotangent_laplacian,
    fit_dome,
)
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh

P_REF = 101325.0 + 3000.0


@cache
def _mesh() -> Mesh:
    return Mesh.preset("coarse")


@cache
def _camera() -> Camera:
    return replace(Camera.d405(), fx=192.6, fy=192.6, cx=154.0, cy=120.8, width=320, height=240)


@cache
def _reference_depth() -> np.ndarray:
    m = _mesh()
    return ref.render_depth(m.vertices, m.triangles, _camera())


def _indent_shape() -> np.ndarray:
    V = _mesh().vertices
    c = np.exp(-((V[:, 0] - 0.01) ** 2 + V[:, 1] ** 2) / (2 * 0.008**2))
    c[_mesh().boundary] = 0.0
    return c  # type: ignore[no-any-return]


@cache
def _indented_depth(depth_m: float = 4e-3) -> np.ndarray:
    m = _mesh()
    n = ref.vertex_normals(m.vertices, m.triangles)
    U = -depth_m * _indent_shape()[:, None] * n
    return ref.render_depth(m.vertices + U, m.triangles, _camera())


def _estimator(**settings: object) -> FrictionlessEstimator:
    ref_obj = SimpleNamespace(depth=_reference_depth(), pressure_pa=P_REF)
    fs = FrictionlessSettings(pixel_stride=2, **settings)  # type: ignore[arg-type]
    return FrictionlessEstimator(_mesh(), _camera(), ref_obj, settings=fs)


def test_cotangent_laplacian_is_symmetric_psd_with_constant_nullspace() -> None:
    m = _mesh()
    L = cotangent_laplacian(m.vertices, m.triangles)
    assert abs(L - L.T).max() < 1e-12
    assert np.abs(L @ np.ones(m.n_nodes)).max() < 1e-10
    ev = np.linalg.eigvalsh(L.toarray())
    assert ev.min() > -1e-10 and ev.max() > 0.1


def test_dome_fit_matches_preset_geometry() -> None:
    m = _mesh()
    d = fit_dome(m.vertices, m.triangles, m.boundary)
    assert d.height == pytest.approx(0.030, rel=0.02)
    # Equivalent half-width of a 57.25 x 40 mm ellipse.
    assert d.half_width == pytest.approx(np.sqrt(0.05725 * 0.040), rel=0.03)
    assert d.radius == pytest.approx((d.half_width**2 + d.height**2) / (2 * d.height))


def test_tension_from_rest_pressure_young_laplace() -> None:
    est = _estimator()
    assert est.rest_gauge_pa == pytest.approx(3000.0)
    assert est.T0 == pytest.approx(0.5 * 3000.0 * est.dome.radius)
    assert _estimator(T0=123.0).T0 == 123.0


def test_identical_frames_give_no_contact_and_zero_force() -> None:
    est = _estimator()
    e = est.process(Frame(rgb=None, depth=_reference_depth(), pressure_pa=P_REF))
    assert not e.contact.any()
    assert np.linalg.norm(e.net_force) < 1e-3
    assert np.abs(e.displacements).max() < 1e-5


def test_inward_indentation_gives_inward_force_and_contact_at_indent() -> None:
    est = _estimator()
    e = est.process(Frame(rgb=None, depth=_indented_depth(), pressure_pa=P_REF))
    assert e.info.status == "solved"
    # Inward = into the bubble = -z near the top of the dome.
    assert e.net_force[2] < -0.2
    assert abs(e.net_force[2]) > 3 * np.hypot(*e.net_force[:2])
    c = _indent_shape()
    assert e.contact.any()
    assert np.all(c[e.contact] > 0.2)  # contact only where the indenter pressed
    assert e.contact[int(np.argmax(c))]
    # Observed normal displacement at the indent centre is inward, of the right size.
    top = int(np.argmax(c))
    u_top = e.displacements[top] @ est.normals[top]
    assert -6e-3 < u_top < -2e-3


def test_recovers_pressure_generated_by_its_own_forward_model() -> None:
    """Pressure patch -> equilibrium + gas displacement -> ray-cast depth -> estimate."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    est = _estimator()
    m = _mesh()
    interior, a = est.interior, est.areas
    L = cotangent_laplacian(m.vertices, m.triangles)[interior][:, interior]
    V = m.vertices
    pc = -2500.0 * np.exp(-((V[:, 0] - 0.01) ** 2 + V[:, 1] ** 2) / (2 * 0.006**2))
    pc[m.boundary] = 0.0
    gas = est.P0 / est.V0
    system = sp.bmat(
        [
            [est.T0 * L, sp.csr_matrix(-a[interior][:, None])],
            [sp.csr_matrix(gas * a[interior][None, :]), sp.csr_matrix([[1.0]])],
        ]
    ).tocsc()
    sol = spl.spsolve(system, np.concatenate([a[interior] * pc[interior], [0.0]]))
    u = np.zeros(m.n_nodes)
    u[interior] = sol[:-1]
    assert u.min() < -1e-3  # a real dent, about 1.6 mm
    depth = ref.render_depth(V + u[:, None] * est.normals, m.triangles, _camera())
    e = est.estimate_depth(depth, P_REF)
    f_true = ((a * pc)[:, None] * est.normals)[m.interior].sum(axis=0)
    assert np.linalg.norm(e.net_force - f_true) < 0.05 * np.linalg.norm(f_true)
    assert est.last_pv == pytest.approx(sol[-1], rel=0.05)
    assert np.array_equal(e.contact, -pc > 2000.0)


def test_contact_pressure_nonnegative_and_normal() -> None:
    est = _estimator()
    e = est.process(Frame(rgb=None, depth=_indented_depth(), pressure_pa=P_REF))
    assert np.all(e.normal_pressure >= 0.0)
    # Frictionless: every node force is along its normal, pointing inward.
    along = np.einsum("ij,ij->i", e.node_forces, est.normals)
    assert np.allclose(np.cross(e.node_forces, est.normals), 0.0, atol=1e-12)
    assert np.all(along <= 1e-12)
    assert np.all(e.node_forces[est.boundary] == 0.0)


def test_nan_and_zero_pixels_give_finite_outputs() -> None:
    est = _estimator()
    d = _indented_depth().copy()
    d[60:120, 100:160] = np.nan
    d[130:150, :] = 0.0
    d[5, 7] = np.inf
    e = est.process(Frame(rgb=None, depth=d, pressure_pa=P_REF))
    for name in ("node_forces", "contact_pressure", "normal_pressure", "net_force"):
        assert np.all(np.isfinite(getattr(e, name))), name
    assert 0.0 < e.valid_node_fraction < 1.0
    # Back to a clean frame: the full mask is restored.
    e2 = est.process(Frame(rgb=None, depth=_indented_depth(), pressure_pa=P_REF))
    assert e2.valid_node_fraction > e.valid_node_fraction


def test_warm_start_second_identical_solve_same_answer_fewer_iterations() -> None:
    est = _estimator()
    d = _indented_depth()
    e1 = est.estimate_depth(d, P_REF)
    e2 = est.estimate_depth(d, P_REF)
    assert e2.info.iterations < e1.info.iterations
    assert np.allclose(e2.net_force, e1.net_force, rtol=1e-2, atol=1e-3)
    assert np.array_equal(e2.contact, e1.contact)


def test_wrong_depth_shape_is_a_clear_error() -> None:
    est = _estimator()
    with pytest.raises(ValueError, match="camera"):
        est.estimate_depth(np.zeros((10, 10), dtype=np.float32), P_REF)
    with pytest.raises(ValueError, match="depth"):
        est.process(Frame(rgb=None, depth=None, pressure_pa=P_REF))


def test_measured_pressure_mode_uses_pressure_change() -> None:
    est = _estimator(use_measured_pressure=True)
    e = est.estimate_depth(_reference_depth(), P_REF + 200.0)
    assert est.last_pv == pytest.approx(200.0, rel=1e-3)
    assert np.all(np.isfinite(e.net_force))


# ----------------------------------------------------------------------------- real recording
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


def _real_setup(n_frames: int) -> tuple[Mesh, Camera, list[np.ndarray], list[float]]:
    """Untouched Punyo frames: depth from the organised cloud, intrinsics fitted to it, and
    the public implementation's mesh frame (camera rotated 25 degrees about y)."""
    mesh = Mesh.load(SHARED / "reference-mesh-390.vtk")
    depths, pressures = [], []
    for i in range(n_frames):
        pc = np.load(SHARED / "expand" / f"pc_{i}.npy").astype(np.float64)
        z = pc[:, 2].reshape(480, 640)
        depths.append(np.where((z > 0.03) & (z < 0.2), z, 0.0).astype(np.float32))
        pressures.append(100.0 * float(np.load(SHARED / "expand" / f"pressure_{i}.npy")))
        if i == 0:
            ok = (pc[:, 2] > 0.03) & (pc[:, 2] < 0.2)
            v, u = np.divmod(np.arange(len(pc)), 640)
            one = np.ones(int(ok.sum()))
            fx, cx = np.linalg.lstsq(
                np.column_stack([pc[ok, 0] / pc[ok, 2], one]), u[ok], rcond=None
            )[0]
            fy, cy = np.linalg.lstsq(
                np.column_stack([pc[ok, 1] / pc[ok, 2], one]), v[ok], rcond=None
            )[0]
    a = np.radians(25.0)
    rot = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    pose = np.eye(4)
    pose[:3, :3] = rot.T
    cam = Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=640, height=480).with_pose(pose)
    return mesh, cam, depths, pressures


@pytest.mark.skipif(not SHARED.exists(), reason="../shared/data is not beside this clone")
def test_real_untouched_frames_give_small_force_and_little_contact() -> None:
    mesh, cam, depths, pressures = _real_setup(8)
    stack = np.stack(depths[:5])
    ref_depth = np.where((stack > 0).all(axis=0), stack.mean(axis=0), 0.0).astype(np.float32)
    reference = SimpleNamespace(depth=ref_depth, pressure_pa=float(np.mean(pressures[:5])))
    est = FrictionlessEstimator(mesh, cam, reference)
    # Rest pressure about 1065.8 hPa absolute: gauge about 5.3 kPa.
    assert 4000.0 < est.rest_gauge_pa < 6500.0
    for d, p in zip(depths[5:], pressures[5:], strict=True):
        e = est.estimate_depth(d, p)
        assert e.info.status == "solved"
        assert np.linalg.norm(e.net_force) < 0.5
        assert e.contact.mean() < 0.02


def test_contact_threshold_taken_from_config() -> None:
    ref_obj = SimpleNamespace(depth=_reference_depth(), pressure_pa=P_REF)
    strict = SimpleNamespace(k_const=1e9, k_linear=2.0)
    est = FrictionlessEstimator(
        _mesh(), _camera(), ref_obj, strict, settings=FrictionlessSettings(pixel_stride=2)
    )
    e = est.estimate_depth(_indented_depth(), P_REF)
    assert est.k_const == 1e9 and not e.contact.any()
    est.reconfigure(k_const=2000.0)
    assert est.estimate_depth(_indented_depth(), P_REF).contact.any()


def test_pipeline_refuses_a_parameter_the_frictionless_estimator_lacks() -> None:
    from bubble_rt.estimation.deformation import Reference
    from bubble_rt.estimation.pipeline import Pipeline

    reference = Reference.capture(Frame(None, _reference_depth(), P_REF))
    pipe = Pipeline(_mesh(), _camera(), reference, kind="frictionless")
    assert pipe.tracker is None and pipe.params == ("k_const", "k_linear")
    config = pipe.config
    with pytest.raises(ValueError, match="no parameter k_f"):
        pipe.reconfigure({"k_f": 0.5, "k_const": 1500.0})
    assert pipe.config == config and pipe.estimator.k_const == 2000.0
    pipe.reconfigure({"k_const": 1500.0})
    assert pipe.estimator.k_const == 1500.0 and pipe.config.k_const == 1500.0
    e = pipe.process(Frame(None, _indented_depth(), P_REF))
    assert e.contact.any()
