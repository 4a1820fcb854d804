"""ADMM group-lasso solver: agreement with a CVXPY + Clarabel reference and hard cases."""

from __future__ import annotations

import functools
import threading

import numpy as np
import pytest
from bubble_rt.estimation.membrane import Material, MembraneModel
from bubble_rt.estimation.solver import GroupLassoSolver, SolverResult, SolverSettings
from bubble_rt.mesh import MIN_ANGLE_DEG, Mesh, triangle_angles_deg
from hypothesis import given, settings
from hypothesis import strategies as st

K_F, K_U = 0.3322, 537592.0
K_CONST, K_LINEAR = 2000.0, 2.0
STATUSES = {"solved", "max_iter_reached", "time_limit_reached", "non_finite_input"}


@functools.cache
def _model(name: str = "coarse", E: float = 1.317e6) -> MembraneModel:
    return MembraneModel(Mesh.preset(name), Material(E=E))


def synthetic_field(
    mesh: Mesh,
    kind: str = "indent",
    depth: float = 8e-3,
    noise: float = 2e-4,
    seed: int = 0,
    centre: tuple[float, float] = (0.01, 0.005),
) -> tuple[np.ndarray, float]:
    """A smooth contact-like displacement (m) plus Gaussian noise, and a matching dp (Pa)."""
    V = mesh.vertices
    r = np.linalg.norm(V[:, :2] - np.asarray(centre), axis=1)
    bump = np.exp(-((r / 0.015) ** 2))
    n = np.zeros_like(V)
    n[:, 2] = 1.0
    U = -depth * bump[:, None] * n
    if kind == "shear":
        U[:, 0] += 0.6 * depth * bump
    U[mesh.boundary] = 0.0
    rng = np.random.default_rng(seed)
    U = U + rng.normal(scale=noise, size=U.shape)
    return np.ascontiguousarray(U), 40_000.0 * depth


def objective(model: MembraneModel, U: np.ndarray, dp: float, dU: np.ndarray) -> float:
    """The group-lasso objective of docs/method.md, "How the solver works" (dimensionless)."""
    n = model.n_nodes
    rim = ~model.mesh.interior
    w = np.where(rim, K_F * rim.sum() / n, K_F)
    F = model.external_forces(U + dU, dp)
    return float(w @ np.linalg.norm(F, axis=1) + K_U / n * np.sum(dU**2))


@functools.cache
def _problem(name: str):
    from bubble_rt.reference import GroupLassoProblem

    mesh = Mesh.preset(name)
    return GroupLassoProblem(mesh.vertices, mesh.triangles, mesh.boundary, k_f=K_F, k_u=K_U)


@functools.cache
def _reference(name: str, kind: str) -> tuple[np.ndarray, float]:
    """bubble_rt.reference (CVXPY + Clarabel) at tight tolerance: (dU, objective)."""
    U, dp = synthetic_field(_model(name).mesh, kind)
    return _problem(name).solve(U, dp, tight=True)


def _solve(model: MembraneModel, U, dp, settings=None, k_f=K_F, k_u=K_U) -> SolverResult:
    s = GroupLassoSolver(model, k_f, k_u, settings)
    return s.solve_frame(U, dp)


def _check_against_reference(name: str, kind: str, settings: SolverSettings, gap_tol: float):
    model = _model(name)
    U, dp = synthetic_field(model.mesh, kind)
    dU_ref, obj_ref = _reference(name, kind)
    res = _solve(model, U, dp, settings)
    assert res.info.status == "solved"
    obj = _problem(name).objective(res.dU, U, dp)
    assert obj == pytest.approx(res.info.objective, rel=1e-9)
    assert objective(model, U, dp, res.dU) == pytest.approx(obj, rel=1e-9)
    gap = (obj - obj_ref) / obj_ref
    assert -1e-7 <= gap <= gap_tol
    # Exact rim constraint.
    assert np.array_equal(
        (U + res.dU)[model.mesh.boundary], np.zeros((len(model.mesh.boundary), 3))
    )
    # Contact sets agree except at nodes within 2 % of the threshold.
    F, F_ref = (model.external_forces(U + d, dp) for d in (res.dU, dU_ref))
    p, p_ref = model.normal_pressure(F), model.normal_pressure(F_ref)
    thresh = max(K_CONST, K_LINEAR * (model.areas @ p_ref) / model.areas.sum())
    c, c_ref = (model.contact_mask(x, K_CONST, K_LINEAR) for x in (p, p_ref))
    differ = c != c_ref
    assert np.all(np.abs(p_ref[differ] - thresh) <= 0.02 * thresh)
    assert c_ref.sum() > 0
    # Net force within 1 %.
    f, f_ref = model.net_force(F), model.net_force(F_ref)
    assert np.linalg.norm(f - f_ref) <= 0.01 * np.linalg.norm(f_ref)


@pytest.mark.parametrize("kind", ["indent", "shear"])
@pytest.mark.parametrize("name", ["coarse", "medium", "fine"])
def test_matches_reference_at_default_settings(name, kind):
    _check_against_reference(name, kind, SolverSettings(), 1e-3)


@pytest.mark.parametrize("kind", ["indent", "shear"])
@pytest.mark.parametrize("name", ["coarse", "medium", "fine"])
def test_matches_reference_at_tight_settings(name, kind):
    _check_against_reference(name, kind, SolverSettings.tight(), 1e-5)


# ------------------------------------------------------------------------- hard cases
def _assert_honest(res: SolverResult, model: MembraneModel, U, dp, settings=None):
    assert res.info.status in STATUSES
    assert np.isfinite(res.dU).all() and np.isfinite(res.dual).all()
    assert np.isfinite(res.info.objective)
    s = settings or SolverSettings()
    if res.info.status == "solved":
        assert res.info.duality_gap <= s.eps_abs + s.eps_rel * res.info.objective + 1e-12
    # Never worse than not correcting at all (dU = -U on the rim only).
    dU0 = np.zeros_like(U)
    dU0[model.mesh.boundary] = -U[model.mesh.boundary]
    if res.info.status == "solved":
        assert res.info.objective <= objective(model, U, dp, dU0) * (1 + 1e-3) + 1e-12


def test_zero_input():
    model = _model()
    U = np.zeros((model.n_nodes, 3))
    res = _solve(model, U, 0.0)
    assert res.info.status == "solved"
    assert np.array_equal(res.dU, np.zeros_like(U))
    assert res.info.objective == 0.0


def test_dp_only():
    model = _model()
    U = np.zeros((model.n_nodes, 3))
    res = _solve(model, U, 500.0)
    _assert_honest(res, model, U, 500.0)
    assert res.info.status == "solved"
    assert res.info.objective <= objective(model, U, 500.0, np.zeros_like(U)) + 1e-12


def test_noise_only():
    model = _model("medium")
    rng = np.random.default_rng(3)
    U = rng.normal(scale=2e-4, size=(model.n_nodes, 3))
    res = _solve(model, U, 0.0)
    assert res.info.status == "solved"
    F = model.external_forces(U + res.dU, 0.0)
    F_raw = model.external_forces(np.where(model.mesh.interior[:, None], U, 0.0), 0.0)
    # The group lasso removes most of the noise force.
    assert np.linalg.norm(model.net_force(F)) < 0.2 * np.abs(F_raw).sum(axis=1).max()
    assert np.abs(F).sum() < 0.5 * np.abs(F_raw).sum()


def test_indentation_of_half_the_dome_height():
    model = _model("medium")
    depth = 0.5 * model.mesh.vertices[:, 2].max()
    U, dp = synthetic_field(model.mesh, depth=depth)
    res = _solve(model, U, dp)
    _assert_honest(res, model, U, dp)
    assert res.info.status == "solved"
    F = model.external_forces(U + res.dU, dp)
    assert model.net_force(F)[2] < 0  # the object pushes the membrane down (inward)


@pytest.mark.parametrize("where", ["U_nan", "U_inf", "dp_nan", "dp_inf"])
def test_non_finite_input_raises_and_leaves_state_intact(where):
    model = _model()
    U, dp = synthetic_field(model.mesh)
    a = GroupLassoSolver(model)
    b = GroupLassoSolver(model)
    first = a.solve_frame(U, dp)
    b.solve_frame(U, dp)
    bad_U, bad_dp = U.copy(), dp
    if where == "U_nan":
        bad_U[7, 1] = np.nan
    elif where == "U_inf":
        bad_U[7, 1] = np.inf
    elif where == "dp_nan":
        bad_dp = float("nan")
    else:
        bad_dp = float("inf")
    before = bad_U.copy()
    with pytest.raises(ValueError, match="node 7" if where.startswith("U") else "dp"):
        a.update(bad_U, bad_dp)
    assert np.array_equal(bad_U, before, equal_nan=True)  # nothing written to the input
    U2, dp2 = synthetic_field(model.mesh, seed=5)
    ra, rb = a.solve_frame(U2, dp2), b.solve_frame(U2, dp2)
    assert np.array_equal(ra.dU, rb.dU)
    assert np.isfinite(first.dU).all()


def test_wrong_shape_raises_value_error_naming_argument():
    model = _model()
    s = GroupLassoSolver(model)
    with pytest.raises(ValueError, match="U must have shape"):
        s.update(np.zeros((model.n_nodes - 1, 3)), 0.0)
    with pytest.raises(ValueError, match="primal"):
        s.warm_start(np.zeros((3, 3)), np.zeros((model.n_nodes, 3)))


def _weights_case(k_f: float, k_u: float):
    model = _model()
    U, dp = synthetic_field(model.mesh)
    settings = SolverSettings(max_iter=4000)
    res = _solve(model, U, dp, settings, k_f=k_f, k_u=k_u)
    assert res.info.status in STATUSES
    assert np.isfinite(res.dU).all() and np.isfinite(res.info.objective)
    return res


def test_k_f_tiny():
    res = _weights_case(K_F * 1e-6, K_U)
    assert res.info.status == "solved"


def test_k_f_huge():
    res = _weights_case(K_F * 1e6, K_U)
    assert res.info.status != "non_finite_input"


def test_k_u_tiny():
    res = _weights_case(K_F, K_U * 1e-6)
    assert res.info.status != "non_finite_input"


def test_k_u_huge():
    res = _weights_case(K_F, K_U * 1e6)
    assert res.info.status == "solved"
    # Corrections are too expensive: dU stays tiny on the free nodes.
    assert np.abs(res.dU[_model().mesh.interior]).max() < 1e-5


def test_E_soft_1e3():
    model = _model("coarse", 1e3)
    U, dp = synthetic_field(model.mesh)
    res = _solve(model, U, dp)
    _assert_honest(res, model, U, dp)


def test_E_stiff_1e9():
    model = _model("coarse", 1e9)
    U, dp = synthetic_field(model.mesh)
    res = _solve(model, U, dp)
    _assert_honest(res, model, U, dp)


def _sliver_mesh() -> Mesh:
    """The coarse preset with one interior node slid along an edge until its worst triangle's
    smallest angle is just above the quality bound."""
    base = Mesh.preset("coarse")
    V0, T = base.vertices.copy(), base.triangles
    node = int(np.flatnonzero(base.interior)[len(base.vertices) // 2])
    tri = T[(T == node).any(axis=1)][0]
    other = int(tri[tri != node][0])
    target = MIN_ANGLE_DEG * 1.05

    def worst(t: float) -> float:
        V = V0.copy()
        V[node] = (1 - t) * V0[node] + t * V0[other]
        return float(triangle_angles_deg(V, T).min())

    lo, hi = 0.0, 0.99
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if worst(mid) > target else (lo, mid)
    V = V0.copy()
    V[node] = (1 - lo) * V0[node] + lo * V0[other]
    return Mesh.validated(V, T)


def test_sliver_triangles_just_above_quality_bound():
    mesh = _sliver_mesh()
    assert MIN_ANGLE_DEG < mesh.min_angle_deg() < MIN_ANGLE_DEG * 1.1
    model = MembraneModel(mesh)
    U, dp = synthetic_field(mesh)
    res = _solve(model, U, dp)
    _assert_honest(res, model, U, dp)
    assert res.info.status == "solved"


def test_sudden_jump_warm_start_gives_cold_start_answer():
    model = _model("medium")
    U1, dp1 = synthetic_field(model.mesh, centre=(-0.03, -0.01), depth=2e-3, seed=1)
    U2, dp2 = synthetic_field(model.mesh, centre=(0.03, 0.015), depth=9e-3, seed=2)
    warm = GroupLassoSolver(model)
    warm.solve_frame(U1, dp1)
    rw = warm.solve_frame(U2, dp2)
    rc = _solve(model, U2, dp2)
    assert rw.info.status == rc.info.status == "solved"
    assert rw.info.objective == pytest.approx(rc.info.objective, rel=1e-3)
    fw = model.net_force(model.external_forces(U2 + rw.dU, dp2))
    fc = model.net_force(model.external_forces(U2 + rc.dU, dp2))
    assert np.linalg.norm(fw - fc) <= 0.01 * np.linalg.norm(fc)


def test_same_input_twice_gives_identical_output():
    model = _model()
    U, dp = synthetic_field(model.mesh)
    s = GroupLassoSolver(model)
    a = s.solve_frame(U, dp)
    b = s.solve_frame(U.copy(), dp)
    assert np.array_equal(a.dU, b.dU) and np.array_equal(a.dual, b.dual)
    c = GroupLassoSolver(model).solve_frame(U, dp)
    assert np.array_equal(a.dU, c.dU)


def test_warm_start_converges_faster_on_a_sequence():
    model = _model("medium")
    s = GroupLassoSolver(model)
    cold = SolverSettings(warm_start=False)
    c = GroupLassoSolver(model, settings=cold)
    warm_its, cold_its = 0, 0
    for k in range(4):
        U, dp = synthetic_field(model.mesh, centre=(0.01 + 0.002 * k, 0.005), seed=10 + k)
        warm_its += s.solve_frame(U, dp).info.iterations
        cold_its += c.solve_frame(U, dp).info.iterations
    assert warm_its < cold_its


def test_max_iter_is_a_status_not_an_error():
    model = _model()
    U, dp = synthetic_field(model.mesh)
    res = _solve(model, U, dp, SolverSettings(max_iter=3, eps_rel=1e-12, eps_abs=1e-14))
    assert res.info.status == "max_iter_reached"
    assert res.info.iterations == 3
    assert np.isfinite(res.dU).all()


def test_time_limit_is_a_status_not_an_error():
    model = _model("fine")
    U, dp = synthetic_field(model.mesh)
    s = GroupLassoSolver(model, K_F, K_U, SolverSettings(time_limit=1e-4, check_interval=1))
    s.solve_frame(U, dp)  # cold: runs on to certification
    s.set_settings(SolverSettings(time_limit=1e-4, eps_rel=1e-12, check_interval=1))
    res = s.solve_frame(1.01 * U, dp)
    assert res.info.status == "time_limit_reached"
    assert np.isfinite(res.dU).all()


def test_time_limit_does_not_cut_a_cold_solve():
    # Stopped early, a cold solve's multipliers sit on their bounds almost everywhere and its
    # support is noise; the time limit binds only warm-started solves.
    model = _model("fine")
    U, dp = synthetic_field(model.mesh)
    cold = _solve(model, U, dp, SolverSettings(time_limit=1e-4, check_interval=1))
    untimed = _solve(model, U, dp, SolverSettings(check_interval=1))
    assert cold.info.status == "solved"
    assert cold.info.iterations == untimed.info.iterations


@pytest.mark.parametrize(
    "bad", [dict(alpha=2.5), dict(rho=-1.0), dict(max_iter=0), dict(eps_abs=0.0, eps_rel=0.0)]
)
def test_settings_reject_bad_values(bad):
    with pytest.raises(ValueError):
        SolverSettings(**bad)


def test_set_weights_and_settings_change_the_answer():
    model = _model()
    U, dp = synthetic_field(model.mesh)
    s = GroupLassoSolver(model)
    a = s.solve_frame(U, dp)
    s.set_weights(K_F * 10, K_U)
    b = s.solve_frame(U, dp)
    assert b.info.objective > a.info.objective
    s.set_weights(K_F, K_U)
    s.set_settings(SolverSettings.tight())
    c = s.solve_frame(U, dp)
    assert c.info.status == "solved"
    assert c.info.objective <= a.info.objective * (1 + 1e-9)


def test_gil_is_released_while_solving():
    model = _model("medium")
    U, dp = synthetic_field(model.mesh)
    s = GroupLassoSolver(
        model, settings=SolverSettings(max_iter=2000, eps_rel=1e-14, eps_abs=1e-16)
    )
    s.update(U, dp)
    counter = [0]
    during: list[int] = []
    done = threading.Event()

    def work() -> None:
        c0 = counter[0]
        res = s.solve()
        during.append(counter[0] - c0)
        during.append(res.info.iterations)
        done.set()

    t = threading.Thread(target=work)
    t.start()
    while not done.is_set():
        counter[0] += 1
    t.join()
    # While C++ iterated (hundreds of ms) this thread kept counting; holding the GIL would
    # have frozen it for the whole solve.
    assert during[1] == 2000
    assert during[0] > 10_000


def test_iterations_do_not_depend_on_units():
    # The same problem in millimetres (N/mm^2 for E and dp, 1/mm^2 for k_u) runs the same
    # iterations and gives the same answer, because rho follows the data.
    mesh = Mesh.preset("coarse")
    U, dp = synthetic_field(mesh)
    mat = Material()
    si = _solve(MembraneModel(mesh, mat), U, dp)
    mesh_mm = Mesh(mesh.vertices * 1e3, mesh.triangles, mesh.boundary)
    mat_mm = Material(E=mat.E * 1e-6, nu=mat.nu, thickness=mat.thickness * 1e3)
    mm = _solve(MembraneModel(mesh_mm, mat_mm), U * 1e3, dp * 1e-6, k_u=K_U * 1e-6)
    assert mm.info.status == si.info.status == "solved"
    assert abs(mm.info.iterations - si.info.iterations) <= 5
    assert mm.info.objective == pytest.approx(si.info.objective, rel=1e-3)
    assert np.allclose(mm.dU * 1e-3, si.dU, atol=1e-3 * np.abs(si.dU).max())


@settings(max_examples=12, deadline=None)
@given(
    depth=st.floats(0.0, 0.012),
    noise=st.floats(0.0, 5e-4),
    x=st.floats(-0.03, 0.03),
    y=st.floats(-0.02, 0.02),
    kind=st.sampled_from(["indent", "shear"]),
    seed=st.integers(0, 1000),
)
def test_solution_properties_hold_for_random_contacts(depth, noise, x, y, kind, seed):
    # Whatever the contact: exact rim, finite output, a certified gap when "solved", never
    # worse than leaving the displacements uncorrected, and the reported objective is the
    # objective of the returned dU.
    model = _model()
    U, dp = synthetic_field(model.mesh, kind, depth=depth, noise=noise, seed=seed, centre=(x, y))
    res = _solve(model, U, dp)
    assert res.info.status == "solved"
    _assert_honest(res, model, U, dp)
    assert np.all((U + res.dU)[model.mesh.boundary] == 0.0)
    assert res.info.objective == pytest.approx(objective(model, U, dp, res.dU), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("name", ["coarse", "medium"])
def test_contact_made_and_released_between_frames_stays_fast(name):
    # Untouched -> firm contact -> released, each switch within one frame. rho follows the
    # previous solution's forces (tiny, then large, then tiny again) and is re-set inside the
    # solve when the frame differs; every frame must still be certified in few iterations
    # (deterministic counts; the raw-force rule took 190-205 on the first untouched frame).
    model = _model(name)
    s = GroupLassoSolver(model, K_F, K_U)
    steps = [(0.0, 1), (0.0, 2), (10e-3, 3), (10e-3, 4), (0.0, 5), (0.0, 6), (10e-3, 7)]
    for depth, seed in steps:
        U, dp = synthetic_field(model.mesh, depth=depth, noise=1e-4, seed=seed)
        res = s.solve_frame(U, dp)
        assert res.info.status == "solved"
        assert res.info.iterations <= 120, (depth, seed, res.info.iterations)


def test_every_rho_a_run_visits_stays_factored():
    # Untouched frames swing rho with their noise, contacts take it down by decades: this
    # sequence ends its solves at 11 rho values and passes through more inside them. Played
    # twice, the second pass must factor nothing (a 12-factor cache refactored 3 of its 12
    # frames, each a full numeric factorization: the slowest solves of a daemon run).
    model = _model("coarse")
    s = GroupLassoSolver(model, K_F, K_U)
    frames = [
        synthetic_field(model.mesh, depth=depth, noise=noise, seed=k)
        for k, (depth, noise) in enumerate(
            [(0.0, 1e-5), (0.0, 1e-3), (16e-3, 1e-4), (0.0, 3e-5), (0.5e-3, 1e-4), (0.0, 3e-4)]
            + [(4e-3, 1e-5), (0.0, 1e-4), (1e-3, 3e-4), (8e-3, 1e-3), (0.0, 1e-5), (2e-3, 1e-5)]
        )
    ]
    first = [s.solve_frame(U, dp).info for U, dp in frames]
    assert len({round(4 * np.log10(i.rho)) for i in first}) >= 10
    assert sum(i.factorizations for i in first) >= 9
    again = [s.solve_frame(U, dp).info for U, dp in frames]
    assert all(i.status == "solved" for i in first + again)
    assert [i.factorizations for i in again] == [0] * len(frames)
    assert all(i.setup_time_ms == 0.0 for i in again)


def test_contact_onset_frame_drops_rho_when_its_gap_stalls():
    # The first frame of a touch after untouched ones starts at the untouched frames' large rho,
    # and its own iterate cannot show that its forces grew: they grow only as fast as that rho
    # lets them, so its duality gap stalls (kStallGapFraction, cpp/group_lasso.cpp).
    # Calibration seed 1000's first round press (tracked by the simulator's oracle, so no
    # images), medium mesh: its first frame in contact (frame 15, 0.25 N) took 132 iterations
    # before the stall rule and 55 with it; the frames before it are unchanged.
    from bubble_rt.estimation.deformation import FlowSettings
    from bubble_rt.estimation.pipeline import Pipeline
    from bubble_rt.eval import estimator_mesh, simulate_trajectory

    traj = simulate_trajectory("round", 0, 24, 1000, render=False)  # its timing: 24 frames
    pipe = Pipeline.capture(
        traj.reference_frames,
        traj.camera,
        mesh=estimator_mesh("medium", traj),
        fit=False,
        flow=FlowSettings(method="oracle"),
    )
    est = [pipe.process(f) for f in traj.frames[:16]]
    truth = [np.linalg.norm(f.truth.net_force) for f in traj.frames[:16]]
    onset = next(k for k, e in enumerate(est) if e.contact.any())
    assert all(t < 0.12 for t in truth[:onset]) and truth[onset] > 0.2
    assert est[onset].info.status == "solved"
    assert est[onset].info.iterations <= 80, est[onset].info.iterations


def test_reported_certificate_belongs_to_the_returned_displacements():
    # A x is carried along the iterations, checks come early when the gap's rate predicts
    # certification, and factors at a new rho reuse the first one's symbolic analysis: the
    # reported objective must still be the objective of the returned dU, recomputed here from
    # scratch, on frames that move rho (untouched -> contact -> released).
    model = _model("medium")
    s = GroupLassoSolver(model, K_F, K_U)
    tol = SolverSettings().eps_abs + SolverSettings().eps_rel
    rhos = set()
    for depth, seed in [(0.0, 1), (10e-3, 2), (10e-3, 3), (0.0, 4), (6e-3, 5)]:
        U, dp = synthetic_field(model.mesh, depth=depth, noise=1e-4, seed=seed)
        res = s.solve_frame(U, dp)
        assert res.info.status == "solved"
        recomputed = objective(model, U, dp, res.dU)
        assert res.info.objective == pytest.approx(recomputed, rel=1e-9)
        assert res.info.duality_gap <= tol * max(recomputed, 1.0)
        rhos.add(res.info.rho)
    assert len(rhos) >= 2  # the sequence did refactor


def test_overflowing_data_reports_non_finite_input():
    # Finite inputs whose forces overflow double precision: a status, not an exception.
    model = MembraneModel(Mesh.preset("coarse"), Material(E=1e300))
    U = np.full((model.n_nodes, 3), 1e12)
    res = _solve(model, U, 0.0)
    assert res.info.status == "non_finite_input"
    assert np.isfinite(res.dU).all()


@pytest.mark.parametrize(
    "changes",
    [
        dict(scaling_iter=10),
        dict(adaptive_rho=True),
        dict(anderson_memory=0),
        dict(alpha=1.0),
        dict(sigma=0.0),
    ],
    ids=["ruiz", "adaptive_rho", "no_anderson", "no_relaxation", "no_sigma"],
)
def test_optional_algorithm_paths_reach_the_reference(changes):
    model = _model("coarse")
    U, dp = synthetic_field(model.mesh)
    _, obj_ref = _reference("coarse", "indent")
    res = _solve(model, U, dp, SolverSettings(**changes))
    assert res.info.status == "solved"
    assert -1e-7 <= (res.info.objective - obj_ref) / obj_ref <= 1e-3
