"""Tests of the paper-faithful reference (bubble_rt.reference)."""

from __future__ import annotations

from dataclasses import replace
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from bubble_rt import reference as ref
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh

E, NU, THICK = 1.317e6, 0.5, 0.65e-3


@cache
def _mesh(name: str = "coarse") -> Mesh:
    return Mesh.preset(name)


@cache
def _problem(name: str = "coarse") -> ref.GroupLassoProblem:
    m = _mesh(name)
    return ref.GroupLassoProblem(m.vertices, m.triangles, m.boundary, E, NU, THICK)


def _flat_square(n: int = 6, side: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Flat (z = 0) structured square patch, n x n nodes, normals +z."""
    g = np.linspace(0.0, side, n)
    X, Y = np.meshgrid(g, g, indexing="xy")
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(n * n)])
    tris = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            if (i + j) % 2:
                tris += [(a, b, d), (a, d, c)]
            else:
                tris += [(a, b, c), (b, d, c)]
    return V, np.asarray(tris)


def _indentation(m: Mesh, depth: float, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    V = m.vertices
    n = ref.vertex_normals(V, m.triangles)
    c = np.exp(-((V[:, 0] - 0.01) ** 2 + V[:, 1] ** 2) / (2 * 0.012**2))
    U = -depth * c[:, None] * n
    U += noise * np.random.default_rng(seed).standard_normal(U.shape)
    U[m.boundary] = 0.0
    return U  # type: ignore[no-any-return]


# ----------------------------------------------------------------------------- stiffness
def test_stiffness_symmetric_psd() -> None:
    m = _mesh()
    K = ref.stiffness_matrix(m.vertices, m.triangles, E, NU, THICK)
    assert K.shape == (3 * m.n_nodes, 3 * m.n_nodes)
    assert abs(K - K.T).max() == 0.0
    ev = np.linalg.eigvalsh(K.toarray())
    assert ev.min() > -1e-9 * ev.max()


def test_rigid_translation_gives_zero_force() -> None:
    m = _mesh()
    K = ref.stiffness_matrix(m.vertices, m.triangles, E, NU, THICK)
    U = np.tile([1e-3, -2e-3, 0.5e-3], (m.n_nodes, 1))
    F = (K @ U.ravel()).reshape(-1, 3)
    assert np.abs(F).max() < 1e-10


def test_infinitesimal_rotation_gives_zero_force() -> None:
    m = _mesh()
    K = ref.stiffness_matrix(m.vertices, m.triangles, E, NU, THICK)
    w = np.array([0.01, -0.02, 0.03])
    U = np.cross(w, m.vertices)
    F = (K @ U.ravel()).reshape(-1, 3)
    assert np.abs(F).max() < 1e-10
    # A non-rigid field of the same size does produce forces (the test can fail).
    U2 = U * m.vertices[:, :1] * 50
    assert np.abs(K @ U2.ravel()).max() > 1e-4


def test_flat_patch_uniform_stretch_matches_plane_stress() -> None:
    side = 0.02
    V, T = _flat_square(6, side)
    ex, ey = 1e-3, -2e-4
    U = np.column_stack([ex * V[:, 0], ey * V[:, 1], np.zeros(len(V))])
    K = ref.stiffness_matrix(V, T, E, NU, THICK)
    F = (K @ U.ravel()).reshape(-1, 3)
    D = E / (1 - NU**2)
    sxx, syy = D * (ex + NU * ey), D * (ey + NU * ex)
    tol = 1e-12 + 1e-9 * THICK * abs(sxx) * side
    right = np.isclose(V[:, 0], side)
    left = np.isclose(V[:, 0], 0.0)
    top = np.isclose(V[:, 1], side)
    edge = right | left | top | np.isclose(V[:, 1], 0.0)
    # Interior nodes are in equilibrium; edge resultants equal stress x thickness x length.
    assert np.abs(F[~edge]).max() < tol
    assert F[right, 0].sum() == pytest.approx(THICK * sxx * side, rel=1e-9)
    assert F[left, 0].sum() == pytest.approx(-THICK * sxx * side, rel=1e-9)
    assert F[top, 1].sum() == pytest.approx(THICK * syy * side, rel=1e-9)
    assert np.abs(F[:, 2]).max() < tol
    # Mid-edge nodes carry traction x spacing.
    h = side / 5
    mid_right = right & ~np.isclose(V[:, 1], 0.0) & ~top
    assert np.allclose(F[mid_right, 0], THICK * sxx * h, rtol=1e-9)


def test_stiffness_rejects_degenerate_triangle() -> None:
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    with pytest.raises(ValueError, match="degenerate"):
        ref.stiffness_matrix(V, np.array([[0, 1, 2]]), E, NU, THICK)


# ----------------------------------------------------------------------------- areas, normals
def test_lumped_areas_sum_to_surface_area_and_normals_outward() -> None:
    m = _mesh()
    V, T = m.vertices, m.triangles
    a = ref.lumped_areas(V, T)
    total = 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1)
    assert a.sum() == pytest.approx(total.sum(), rel=1e-12)
    n = ref.vertex_normals(V, T)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    top = int(np.argmax(V[:, 2]))
    assert n[top, 2] > 0.99


def test_external_forces_sign_pressure_only() -> None:
    # More internal pressure with no motion needs an inward external force to hold the shape.
    pb = _problem()
    F = pb.forces(np.zeros((pb.n, 3)), 100.0)
    p = ref.normal_pressure(F, pb.areas, pb.normals)
    assert np.allclose(p, 100.0)


# ----------------------------------------------------------------------------- contact / net
def test_contact_mask_rule() -> None:
    a = np.array([1.0, 1.0, 1.0, 1.0])
    p = np.array([0.0, 1500.0, 2500.0, 0.0])
    # mean p = 1000, 2 x mean = 2000 -> threshold max(2000, 2000) = 2000
    assert ref.contact_mask(p, a).tolist() == [False, False, True, False]
    # A large common pressure raises the linear threshold: 2 x 4000 = 8000.
    p2 = np.array([4000.0, 4000.0, 9000.0, -1000.0])
    assert ref.contact_mask(p2, a).tolist() == [False, False, True, False]
    assert ref.contact_mask(p2, a, k_const=10000.0).tolist() == [False] * 4


def test_net_force_excludes_rim() -> None:
    F = np.arange(12, dtype=float).reshape(4, 3)
    assert np.allclose(ref.net_force(F, [0, 3]), F[1] + F[2])


# ----------------------------------------------------------------------------- group lasso
def test_solver_zero_input_gives_zero_correction() -> None:
    pb = _problem()
    dU, obj = pb.solve(np.zeros((pb.n, 3)), 0.0, tight=True)
    assert np.abs(dU).max() < 1e-9
    assert obj < 1e-8


def test_solver_optimum_beats_zero_and_perturbations() -> None:
    pb = _problem()
    m = _mesh()
    U = _indentation(m, 4e-3, noise=2e-4)
    dp = 50.0
    dU, obj = pb.solve(U, dp, tight=True)
    assert pb.rim_violation(dU, U) == 0.0
    assert obj == pytest.approx(pb.objective(dU, U, dp), rel=1e-12)
    f0 = pb.objective(np.zeros_like(U), U, dp)
    assert obj < 0.5 * f0  # noise is mostly removed
    rng = np.random.default_rng(1)
    for scale in (1e-6, 1e-5):
        pert = scale * rng.standard_normal(U.shape)
        pert[m.boundary] = 0.0
        assert obj <= pb.objective(dU + pert, U, dp) + 1e-9 * obj


def test_solver_default_tolerance_close_to_tight() -> None:
    pb = _problem()
    U = _indentation(_mesh(), 3e-3, noise=1e-4, seed=3)
    _, obj_tight = pb.solve(U, 20.0, tight=True)
    _, obj = pb.solve(U, 20.0)
    assert abs(obj - obj_tight) <= 1e-4 * obj_tight


def test_solver_rejects_bad_input() -> None:
    pb = _problem()
    U = np.zeros((pb.n, 3))
    U[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        pb.solve(U, 0.0)
    with pytest.raises(ValueError, match="x 3"):
        pb.solve(np.zeros((pb.n - 1, 3)), 0.0)


# ----------------------------------------------------------------------------- ray casting
def test_render_depth_matches_mesh_vertices() -> None:
    m = _mesh()
    cam = Camera.d405()
    depth = ref.render_depth(m.vertices, m.triangles, cam)
    uv, z = cam.project(m.vertices)
    top = int(np.argmax(m.vertices[:, 2]))
    u, v = np.round(uv[top]).astype(int)
    assert depth[v, u] == pytest.approx(z[top], abs=5e-4)
    assert np.all(depth[depth > 0] >= 0.075 - 1e-9)
    assert (depth > 0).mean() > 0.3


# ----------------------------------------------------------------------------- pipeline
def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 2.0)
    img = (255 * (img - img.min()) / (img.max() - img.min())).astype(np.uint8)
    return np.repeat(img[:, :, None], 3, axis=2)  # type: ignore[no-any-return]


def test_pipeline_recovers_displacements_of_a_consistent_warp() -> None:
    import cv2
    from scipy.interpolate import griddata

    m = _mesh()
    cam = replace(Camera.d405(), fx=192.6, fy=192.6, cx=154.0, cy=120.8, width=320, height=240)
    V = m.vertices
    U_true = _indentation(m, 3e-3)
    rgb_ref = _texture(cam.height, cam.width, seed=4)
    # Each pixel of the current image shows the texture point it showed in the reference.
    uv0, _ = cam.project(V)
    uv1, _ = cam.project(V + U_true)
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    back = np.asarray(griddata(uv1, uv0 - uv1, (xx, yy), method="linear", fill_value=0.0))
    back = back.astype(np.float32)
    rgb_cur = cv2.remap(rgb_ref, xx + back[..., 0], yy + back[..., 1], cv2.INTER_LINEAR)
    pipe = ref.ReferencePipeline(
        V, m.triangles, m.boundary, cam, rgb_ref, ref.render_depth(V, m.triangles, cam), 0.0
    )
    out = pipe.process_frame(
        Frame(rgb=rgb_cur, depth=ref.render_depth(V + U_true, m.triangles, cam), pressure_pa=0.0)
    )
    err = np.sqrt(((out["raw_displacements"] - U_true) ** 2).sum(axis=1).mean())
    rms = np.sqrt((U_true**2).sum(axis=1).mean())
    assert err < 0.15 * rms
    assert out["net_force"][2] < 0


def test_pipeline_on_synthetic_warp_returns_finite_outputs() -> None:
    import cv2

    m = _mesh()
    cam = replace(Camera.d405(), fx=192.6, fy=192.6, cx=154.0, cy=120.8, width=320, height=240)
    depth_ref = ref.render_depth(m.vertices, m.triangles, cam)
    rgb_ref = _texture(cam.height, cam.width)
    U_true = _indentation(m, 3e-3)
    depth_cur = ref.render_depth(m.vertices + U_true, m.triangles, cam)
    # Shift the texture by 2 px inside a disc around the contact; corrupt a few depth pixels.
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    bump = 2.0 * np.exp(-((xx - 180) ** 2 + (yy - 120) ** 2) / (2 * 25.0**2))
    rgb_cur = cv2.remap(rgb_ref, xx - bump, yy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    depth_cur[100:104, 100:104] = 0.0
    depth_cur[50, 60] = 0.3
    pipe = ref.ReferencePipeline(
        m.vertices, m.triangles, m.boundary, cam, rgb_ref, depth_ref, 101325.0
    )
    out = pipe.process(rgb_cur, depth_cur, 101325.0 + 80.0)
    for key in ("node_forces", "net_force", "normal_pressure", "displacements"):
        assert np.all(np.isfinite(out[key])), key
    assert out["node_forces"].shape == (m.n_nodes, 3)
    assert out["contact"].dtype == bool
    assert set(out["timings_ms"]) == {"flow", "lift", "solve", "post"}
    # The indentation pushes inward: the net force points into the bubble (-z at the top).
    assert out["net_force"][2] < 0
    # Identical frames give zero displacement and no contact.
    same = pipe.process(rgb_ref, depth_ref, 101325.0)
    assert np.abs(same["raw_displacements"]).max() < 1e-6
    assert not same["contact"].any()


SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


@pytest.mark.skipif(not SHARED.exists(), reason="../shared/data is not beside this clone")
def test_pipeline_real_untouched_frame_gives_near_zero_force() -> None:
    mesh = Mesh.load(SHARED / "reference-mesh-390.vtk")
    pcs = [np.load(SHARED / "expand" / f"pc_{i}.npy").astype(np.float64) for i in (0, 1, 2, 6)]
    rgbs = [np.load(SHARED / "expand" / f"rgb_{i}.npy") for i in (0, 1, 2, 6)]
    pres = [100.0 * float(np.load(SHARED / "expand" / f"pressure_{i}.npy")) for i in (0, 1, 2, 6)]
    pc = pcs[0]
    ok = (pc[:, 2] > 0.03) & (pc[:, 2] < 0.2)
    v, u = np.divmod(np.arange(len(pc)), 640)
    one = np.ones(int(ok.sum()))
    fx, cx = np.linalg.lstsq(np.column_stack([pc[ok, 0] / pc[ok, 2], one]), u[ok], rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.column_stack([pc[ok, 1] / pc[ok, 2], one]), v[ok], rcond=None)[0]
    a = np.radians(25.0)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]]).T
    cam = Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=640, height=480).with_pose(pose)
    depths = []
    for p in pcs:
        z = p[:, 2].reshape(480, 640)
        depths.append(np.where((z > 0.03) & (z < 0.2), z, 0.0).astype(np.float32))
    stack = np.stack(depths[:3])
    ref_depth = np.where((stack > 0).all(axis=0), stack.mean(axis=0), 0.0).astype(np.float32)
    ref_rgb = np.stack(rgbs[:3]).astype(np.float32).mean(axis=0).astype(np.uint8)
    pipe = ref.ReferencePipeline(
        mesh.vertices,
        mesh.triangles,
        mesh.boundary,
        cam,
        ref_rgb,
        ref_depth,
        float(np.mean(pres[:3])),
        settings=ref.ReferenceSettings(cloud_stride=4),
    )
    out = pipe.process(rgbs[3], depths[3], pres[3])
    # Real sensor noise moves nodes by a fraction of a millimetre; no contact, ~no force.
    assert np.sqrt((out["raw_displacements"] ** 2).sum(axis=1).mean()) < 1e-3
    assert np.linalg.norm(out["net_force"]) < 0.2
    assert not out["contact"].any()


def test_reconfigure_weights_matches_fresh_problem() -> None:
    m = _mesh()
    U = _indentation(m, 3e-3, noise=1e-4, seed=5)
    pb = ref.GroupLassoProblem(m.vertices, m.triangles, m.boundary, E, NU, THICK)
    pb.reconfigure(k_f=1.0, k_u=1e5)
    _, obj = pb.solve(U, 10.0, tight=True)
    fresh = ref.GroupLassoProblem(
        m.vertices, m.triangles, m.boundary, E, NU, THICK, k_f=1.0, k_u=1e5
    )
    _, obj_fresh = fresh.solve(U, 10.0, tight=True)
    assert obj == pytest.approx(obj_fresh, rel=1e-7)
    assert obj != pytest.approx(_problem().solve(U, 10.0, tight=True)[1], rel=1e-3)
    with pytest.raises(ValueError, match="k_f"):
        pb.reconfigure(k_f=-1.0)


def test_reference_loads_neither_the_cpp_core_nor_the_estimation_package():
    # import-linter cannot see the compiled _core, so this contract is checked by importing.
    import subprocess
    import sys

    code = (
        "import sys, bubble_rt.reference, bubble_rt.reference.pipeline\n"
        "bad = [m for m in sys.modules if m.startswith(('bubble_rt._core', 'bubble_rt.estimation'))]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
