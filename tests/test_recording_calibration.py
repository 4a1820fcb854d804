"""Calibration on recordings with a wrench (issue 12 item 2).

Simulated trajectories are written as recordings in the real layouts (Punyo .npy with
data.json, the project's MCAP with its wrench channel) carrying a wrench the test knows:
``w = R^T f_true + bias`` (plus a torque), R the F/T -> mesh rotation. Calibration on those
recordings must recover the parameters a calibration on the simulated truth directly finds
(same frames, same optimiser, the force term: the recordings carry no contact truth), and R.
"""

from __future__ import annotations

import tomllib
from dataclasses import replace
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from bubble_rt.estimation.deformation import DeformationTracker, FlowSettings, Reference
from bubble_rt.eval import FanOut, estimator_mesh, simulate_trajectory
from bubble_rt.eval import calibration as cal
from bubble_rt.eval import recording_calibration as rc
from bubble_rt.eval.tasks import SimTrajectory
from sim_recordings import (
    rotation,
    saturated_to_invalid,
    with_wrench,
    write_mcap,
    write_punyo,
)

pytestmark = pytest.mark.timeout(900)

MESH = "coarse"
N_FRAMES = 8
N_REF = 3
#: Nelder-Mead budget: with the support within support_tol of the multipliers' bound, 40 ended
#: 0.16 % above the truth's loss (parameters within 4-12 %); 60 reaches it.
MAX_EVALS = 60
#: Pressing trajectories whose forces point different ways (about -z, tilted up to 30 degrees
#: towards different sides), so that a rotation about every axis is observable.
SPECS = (("round", 1), ("round", 3), ("point", 1), ("round", 0))
R_TRUE = rotation((1.0, 2.0, 3.0), 35.0)
BIAS = np.array([0.4, -0.3, 1.2, 0.01, 0.02, -0.03])

#: Tolerances (what they measured when written, coarse mesh, 4 x 8 frames, 40 evaluations):
#: the rotation given: the parameters of the calibration on the truth (measured: identical).
GIVEN_REL_TOL = 1e-3
#: the rotation fitted: E within 15 % of the truth calibration's (measured -1.1 % on the
#: D405-matched camera noise) ...
FITTED_REL_TOL = 0.15
#: k_f and k_u, the flattest directions of the loss (k_f only picks the support), within a
#: factor of 2 (a 3x error fails; measured at the defaults E 0.55 MPa, k_f 0.05: k_f -31 %,
#: k_u -24 %, where the truth's own loss is 0.16 % above its optimum): the loss check below is
#: what guards them, the recovered values fitting the truth within 1 % of its optimum ...
FLAT_FACTOR = 2.0
#: The recovered loss within 0.1 % of the loss at the truth's parameters (a loss that did not
#: move from its start would be 23 % above).
MINIMISED_REL = 1e-3
#: ... and the rotation within 10 degrees of the true one (measured 7.2 degrees; the rest is
#: the estimator's own direction error: the rotation taking the true net forces onto the
#: estimated ones at the truth-calibrated parameters is itself several degrees).
ROTATION_TOL_DEG = 10.0


class _Sum:
    """Several CalibrationProblems (one per trajectory, each on its own fitted mesh) as one."""

    def __init__(self, problems: list[cal.CalibrationProblem]) -> None:
        self.problems = problems

    @property
    def frames(self) -> list[cal.CalibFrame]:
        return [f for p in self.problems for f in p.frames]

    def loss(self, params: dict[str, float], fan: FanOut | None = None) -> float:
        return sum(p.loss(params, fan) for p in self.problems)


@pytest.fixture(scope="module")
def sim() -> SimpleNamespace:
    trajs = []
    for geometry, k in SPECS:
        t = simulate_trajectory(geometry, k, N_FRAMES, cal.CALIB_SEED_BASE, n_reference=N_REF)
        trajs.append(
            SimTrajectory(
                frames=saturated_to_invalid(t.frames),
                reference_frames=saturated_to_invalid(t.reference_frames),
                camera=t.camera,
            )
        )
    # The calibration on the simulated truth directly: the existing CalibrationProblem with
    # the truth's net force, the force term only (lambda2 = 0), like the recordings have.
    problems = []
    for t in trajs:
        mesh = estimator_mesh(MESH, t)
        reference = Reference.capture(t.reference_frames)
        tracker = DeformationTracker(mesh, t.camera, reference, FlowSettings())
        frames = []
        for f in t.frames:
            d = tracker.track(f)
            frames.append(
                cal.CalibFrame(
                    np.asarray(d.U, float),
                    float(d.dp),
                    np.asarray(f.truth.net_force, float),
                    np.asarray(f.truth.contact_mask(mesh), bool),
                )
            )
        # Linearised about the reference's pressure, as the recordings' estimators are.
        factory = partial(rc.fem_at_reference, reference.pressure_pa)
        problems.append(
            cal.CalibrationProblem(
                mesh, frames, factory=factory, weights=cal.LossWeights(lambda2=0.0)
            )
        )
    truth = cal.calibrate(_Sum(problems), max_evals=MAX_EVALS)
    return SimpleNamespace(trajs=trajs, truth=truth, problems=problems)


def _recording_frames(t: SimTrajectory) -> list:
    return with_wrench(list(t.reference_frames) + list(t.frames), R_TRUE, BIAS)


def _rel(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    return {k: a[k] / b[k] - 1.0 for k in cal.PARAMS}


# ------------------------------------------------------------------------------ units
def test_kabsch_recovers_a_known_rotation():
    rng = np.random.default_rng(1)
    W = rng.normal(size=(20, 3))
    R = rotation((0.3, -1.0, 0.5), 80.0)
    np.testing.assert_allclose(rc.kabsch(W, W @ R.T), R, atol=1e-9)
    assert rc.rotation_angle_deg(R, np.eye(3)) == pytest.approx(80.0)
    # A reflection is never returned: the best proper rotation instead.
    got = rc.kabsch(W, -W)
    assert np.linalg.det(got) == pytest.approx(1.0)


def test_wrench_config_reads_rotation_and_names_bad_keys(tmp_path):
    ok = tmp_path / "w.toml"
    ok.write_text("[wrench]\nrotation = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]\nreference_frames = 4\n")
    cfg = rc.load_wrench_config(ok)
    assert cfg["reference_frames"] == 4 and cfg["rotation"][0, 1] == -1.0
    bad = tmp_path / "b.toml"
    bad.write_text("[wrench]\nrotaton = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n")
    with pytest.raises(rc.WrenchCalibrationError, match="wrench.rotaton"):
        rc.load_wrench_config(bad)
    bad.write_text("[wrench]\nrotation = [[1, 0, 0], [0, 2, 0], [0, 0, 1]]\n")
    with pytest.raises(rc.WrenchCalibrationError, match="wrench.rotation: not orthonormal"):
        rc.load_wrench_config(bad)
    bad.write_text("[wrench]\nsign = 2\n")
    with pytest.raises(rc.WrenchCalibrationError, match="wrench.sign must be 1 or -1"):
        rc.load_wrench_config(bad)
    bad.write_text("[wrench]\nsign = -1\n")
    assert rc.load_wrench_config(bad) == {"sign": -1.0}


def test_mcap_recording_round_trips_the_wrench(sim, tmp_path):
    from bubble_rt.io.recordings import open_recording

    t = sim.trajs[0]
    fr = _recording_frames(t)
    path = write_mcap(tmp_path / "r.mcap", fr[N_REF:], fr[:N_REF], t.camera)
    rec = open_recording(path)
    got = [f.wrench for f in rec]
    assert len(got) == N_FRAMES
    np.testing.assert_allclose(np.array(got), np.array([f.wrench for f in fr[N_REF:]]))
    ref = rec.reference_frames(N_REF)  # type: ignore[attr-defined]
    np.testing.assert_allclose(ref[0].wrench, BIAS)


def test_recording_without_wrench_is_refused_naming_the_frame(sim, tmp_path):
    t = sim.trajs[0]
    fr = _recording_frames(t)
    fr[N_REF + 2] = replace(fr[N_REF + 2], wrench=None)
    path = write_mcap(tmp_path / "nowrench.mcap", fr[N_REF:], fr[:N_REF], t.camera)
    with pytest.raises(rc.WrenchCalibrationError, match="frame 2 has no wrench"):
        rc.load_recording(path, mesh=MESH, n_reference=N_REF)


def test_contact_term_only_where_contact_truth_exists(sim):
    t = sim.trajs[0]
    fr = _recording_frames(t)
    # In memory the simulated frames keep their truth: contact truth exists.
    sims = list(t.reference_frames) + list(t.frames)
    with_truth = [replace(a, truth=b.truth) for a, b in zip(fr, sims, strict=True)]
    mem = rc.frames_set("mem", with_truth[:N_REF], with_truth[N_REF:], t.camera, mesh=MESH)
    assert all(f.c_gt is not None for f in mem.frames)
    ev = rc.RecordingProblem([mem], rotation=R_TRUE).evaluate(cal.DEFAULTS)
    assert ev.contact_term > 0
    assert ev.loss == pytest.approx(ev.force_term + 10.0 * ev.contact_term)
    # The same frames as a recording carry no contact truth: the force term alone.
    rec = rc.frames_set("rec", fr[:N_REF], fr[N_REF:], t.camera, mesh=MESH)
    ev2 = rc.RecordingProblem([rec], rotation=R_TRUE).evaluate(cal.DEFAULTS)
    assert ev2.contact_term == 0.0 and ev2.loss == pytest.approx(ev2.force_term)
    assert ev2.force_term == pytest.approx(ev.force_term, rel=1e-9)
    # ... and that force term is the truth calibration's (lambda2 = 0) loss on those frames.
    assert ev2.force_term == pytest.approx(sim.problems[0].loss(cal.DEFAULTS), rel=1e-6)


def test_reaction_sign_is_declared_or_absorbed_by_a_given_improper_rotation(sim):
    t = sim.trajs[1]
    plain = with_wrench(list(t.reference_frames) + list(t.frames), R_TRUE, BIAS)
    # An F/T sensor reporting the reaction: w = -R^T f + bias.
    reaction = with_wrench(list(t.reference_frames) + list(t.frames), -R_TRUE, BIAS)
    a = rc.frames_set("plain", plain[:N_REF], plain[N_REF:], t.camera, mesh=MESH)
    b = rc.frames_set("reaction", reaction[:N_REF], reaction[N_REF:], t.camera, mesh=MESH)
    want = rc.RecordingProblem([a], rotation=R_TRUE).evaluate(cal.DEFAULTS)
    signed = rc.RecordingProblem([b], rotation=R_TRUE, sign=-1.0).evaluate(cal.DEFAULTS)
    improper = rc.RecordingProblem([b], rotation=-R_TRUE).evaluate(cal.DEFAULTS)
    assert signed.loss == pytest.approx(want.loss, rel=1e-9)
    assert improper.loss == pytest.approx(want.loss, rel=1e-9)
    # Fitted with the sign declared: the same rotation as without the sign flip.
    fit_a = rc.RecordingProblem([a]).evaluate(cal.DEFAULTS).rotation
    fit_b = rc.RecordingProblem([b], sign=-1.0).evaluate(cal.DEFAULTS).rotation
    np.testing.assert_allclose(fit_b, fit_a, atol=1e-9)


# ------------------------------------------------------------------------------ recovery
def test_calibration_on_punyo_recordings_recovers_truth_parameters_and_rotation(sim, tmp_path):
    sets = []
    for i, t in enumerate(sim.trajs):
        path = write_punyo(tmp_path / f"punyo-{i}", _recording_frames(t), t.camera)
        # The simulated camera is not the Punyo sensor's: its pose goes to open_recording.
        sets.append(
            rc.load_recording(
                path,
                mesh=MESH,
                n_reference=N_REF,
                pose=t.camera.pose_matrix,
                centre_from_data=False,
            )
        )
    for s in sets:
        np.testing.assert_allclose(s.bias, BIAS, atol=1e-9)
    out = rc.calibrate_recordings(rc.RecordingProblem(sets), max_evals=MAX_EVALS, fit=cal.PARAMS)
    rel = _rel(out.result.params, sim.truth.params)
    angle = rc.rotation_angle_deg(out.rotation, R_TRUE)
    print(f"fitted rotation: parameters vs truth calibration {rel}, rotation error {angle:.2f} deg")

    assert out.rotation_fitted
    truth_loss = _Sum(sim.problems).loss(sim.truth.params)
    print(
        f"truth's loss at the recovered parameters / at its own: "
        f"{_Sum(sim.problems).loss(out.result.params) / truth_loss:.4f}"
    )
    assert abs(rel["E"]) < FITTED_REL_TOL, rel
    for flat in ("k_f", "k_u"):
        assert 1 / FLAT_FACTOR < 1 + rel[flat] < FLAT_FACTOR, rel
    # Where they differ, the recovered parameters fit the truth itself no worse (1 %).
    assert _Sum(sim.problems).loss(out.result.params) <= 1.01 * truth_loss
    assert angle < ROTATION_TOL_DEG
    # The loss at the recovered parameters is no worse than at the truth's (it is minimised), to
    # MINIMISED_REL: k_f picks the support, so the loss is piecewise in it and Nelder-Mead ends
    # on a step near the minimum (measured 0.04 % above the truth's, the same at 60, 80, 100
    # and 120 evaluations and with a restarted simplex; the start is 23 % above).
    at_truth = rc.RecordingProblem(sets).loss(sim.truth.params)
    assert out.result.loss <= (1 + MINIMISED_REL) * at_truth
    # The fitted rotation is far better than knowing nothing (identity: 35 degrees off).
    assert angle < 0.5 * rc.rotation_angle_deg(np.eye(3), R_TRUE)


def _calibrate_given_rotation(paths: list, tmp_path, capsys) -> tuple[str, str, dict[str, float]]:
    """`bubble-rt calibrate --recording ...` with the true rotation given: (stdout, the written
    TOML's text, its parameters named as the truth calibration names them)."""
    from bubble_rt.cli import main

    wcfg = tmp_path / "wrench.toml"
    rows = ", ".join("[" + ", ".join(repr(float(x)) for x in r) + "]" for r in R_TRUE)
    wcfg.write_text(f"[wrench]\nrotation = [{rows}]\nreference_frames = {N_REF}\n")
    out = tmp_path / "calib.toml"
    argv = ["calibrate", "--out", str(out), "--mesh", MESH, "--max-evals", str(MAX_EVALS)]
    argv += ["--wrench-config", str(wcfg), "--workers", "1", "--no-progress", "--fit", "E,k_f,k_u"]
    for p in paths:
        argv += ["--recording", str(p)]
    assert main(argv) == 0
    text = out.read_text()
    est = tomllib.loads(text)["estimator"]
    return (
        capsys.readouterr().out,
        text,
        {"E": est["youngs_modulus"], "k_f": est["k_f"], "k_u": est["k_u"]},
    )


def test_calibrate_command_on_mcap_recordings_with_given_rotation(sim, tmp_path, capsys):
    paths = []
    for i, t in enumerate(sim.trajs):
        fr = _recording_frames(t)
        paths.append(write_mcap(tmp_path / f"rec-{i}.mcap", fr[N_REF:], fr[:N_REF], t.camera))
    text, toml_text, got = _calibrate_given_rotation(paths, tmp_path, capsys)
    assert f"{len(paths)} recordings, {len(paths) * N_FRAMES} frames" in text
    assert "rotation, given" in text
    assert set(tomllib.loads(toml_text)) == {"estimator"}  # the TOML `calibrate` writes on sim data
    rel = _rel(got, sim.truth.params)
    print(f"given rotation: parameters vs truth calibration {rel}")
    assert all(abs(v) < GIVEN_REL_TOL for v in rel.values()), rel
    header = toml_text.split("[estimator]")[0]
    assert "rotation_ft_to_mesh" in header and "# rotation_fitted: false" in header


def test_calibrate_command_names_a_recording_it_cannot_open(tmp_path, capsys):
    from bubble_rt.cli import main

    missing = Path(tmp_path / "nope")
    assert main(["calibrate", "--recording", str(missing), "--no-progress"]) == 2
    assert "nope" in capsys.readouterr().err


def test_calibrate_command_on_ros2_bags_with_given_rotation(sim, tmp_path, capsys):
    """A ROS 2 bag with a WrenchStamped topic calibrates like the project's own recordings
    (bags are one more layout behind `open_recording`)."""
    from bubble_rt.io.bag_writer import write_bag

    paths = []
    for i, t in enumerate(sim.trajs):
        # 32FC1 depth: the kit's 16-bit millimetres would quantise the simulated surface.
        bag = tmp_path / f"bag-{i}"
        write_bag(bag, _recording_frames(t), t.camera, depth_encoding="32FC1", tf=True)
        paths.append(bag)
    text, _, got = _calibrate_given_rotation(paths, tmp_path, capsys)
    assert f"{len(paths)} recordings, {len(paths) * N_FRAMES} frames" in text
    rel = _rel(got, sim.truth.params)
    print(f"bags, given rotation: parameters vs truth calibration {rel}")
    assert abs(rel["E"]) < FITTED_REL_TOL, rel
    for flat in ("k_f", "k_u"):
        assert 1 / FLAT_FACTOR < 1 + rel[flat] < FLAT_FACTOR, rel


#: The simulated bubble's rest gauge pressure (Pa) and the ambient its pressure readings are
#: shifted to: the readings then say 2500 Pa of rest gauge pressure at the default ambient, so
#: an estimator assuming it holds half the true rest tension.
SIM_GAUGE_PA = 5000.0
SHIFTED_AMBIENT_PA = 101325.0 - 2500.0
#: The ambient pressure recovered within this (Pa): 10 % of the rest gauge pressure (measured
#: when written: see the test's print).
AMBIENT_TOL_PA = 0.1 * SIM_GAUGE_PA


def test_calibration_recovers_a_rest_tension_twice_what_the_readings_imply(sim, tmp_path):
    """A bubble whose membrane holds twice the rest tension the defaults assume (its readings
    imply half its true rest gauge pressure): `calibrate --recording --fit ambient_pa` finds
    the ambient pressure that restores it (measured: within 4 Pa), and the force scale."""
    sets = []
    for i, t in enumerate(sim.trajs):
        frames = [
            replace(f, pressure_pa=f.pressure_pa - (101325.0 - SHIFTED_AMBIENT_PA))
            for f in _recording_frames(t)
        ]
        path = write_punyo(tmp_path / f"shifted-{i}", frames, t.camera)
        sets.append(
            rc.load_recording(
                path,
                mesh=MESH,
                n_reference=N_REF,
                pose=t.camera.pose_matrix,
                centre_from_data=False,
            )
        )
    problem = rc.RecordingProblem(sets, rotation=R_TRUE)
    params = {**sim.truth.params}
    before = problem.evaluate({**params, "ambient_pa": 101325.0})
    out = rc.calibrate_recordings(problem, initial=params, max_evals=MAX_EVALS, fit=("ambient_pa",))
    ambient = out.result.params["ambient_pa"]
    print(f"ambient recovered {ambient:.0f} Pa (true {SHIFTED_AMBIENT_PA:.0f})")
    assert abs(ambient - SHIFTED_AMBIENT_PA) < AMBIENT_TOL_PA
    # The force scale comes back (the simulator's dents lean less on the rest tension than
    # the real press does: halving it reads about 9 % less here, half on the real press).
    truth = np.linalg.norm(before.wrenches, axis=1)
    firm = truth >= 1.0
    ratio = lambda F: float(np.median(np.linalg.norm(F, axis=1)[firm] / truth[firm]))  # noqa: E731
    r0, r1 = ratio(before.net_forces), ratio(out.final.net_forces)
    print(f"median |f_est| / |f_true|: {r0:.3f} at the default ambient, {r1:.3f} calibrated")
    assert r0 < 0.95 and abs(r1 - 1.0) < 0.5 * abs(r0 - 1.0)


#: A membrane twice as stiff as the defaults: the simulator's Young's modulus doubled
#: (``PhysicsSpec.youngs_modulus_pa``), on heavy presses (0.3-18 N) whose forces point
#: different ways. Their physics is computed anew (about 30 s each on 2 cores, then cached).
STIFF_FACTOR = 2.0
STIFF_SPECS = (("round", 1), ("round", 3), ("point", 1))
#: The doubled modulus really is stiffer: the same dents need this much more force at least
#: (measured when written: 1.15-1.35 x on frames of 1 N and more).
STIFF_FORCE_GAIN = 1.10
#: The force read within this of the truth: median |f_est| / |f_true| over frames of 1 N and
#: more within 10 % of 1 (measured when written: see the tests' prints).
STIFF_RATIO_TOL = 0.10
#: Where the defaults read clearly off, they read below this (measured when written: 0.74).
STIFF_DEFAULT_BELOW = 0.85


@pytest.fixture(scope="module")
def stiff() -> SimpleNamespace:
    """The trajectories of :data:`STIFF_SPECS` with the doubled modulus, and the gains of their
    true forces over the default membrane's on the same dents."""
    from sim_recordings import stiffer_trajectory

    trajs, gains = [], []
    for geometry, k in STIFF_SPECS:
        t = stiffer_trajectory(geometry, k, N_FRAMES, cal.CALIB_SEED_BASE, STIFF_FACTOR, N_REF)
        soft = simulate_trajectory(
            geometry, k, N_FRAMES, cal.CALIB_SEED_BASE, n_reference=N_REF, render=False
        )
        f = np.array([np.linalg.norm(x.truth.net_force) for x in t.frames])
        f_soft = np.array([np.linalg.norm(x.truth.net_force) for x in soft.frames])
        gains += list(f[f_soft >= 1.0] / f_soft[f_soft >= 1.0])
        trajs.append(t)
    return SimpleNamespace(trajs=trajs, gains=np.array(gains))


def _stiff_problem(stiff: SimpleNamespace, shift_pa: float = 0.0) -> rc.RecordingProblem:
    """The stiff trajectories as recordings (a known wrench, the rotation left to fit), their
    pressure readings lowered by ``shift_pa``."""
    sets = []
    for (geometry, k), t in zip(STIFF_SPECS, stiff.trajs, strict=True):
        fr = [replace(f, pressure_pa=f.pressure_pa - shift_pa) for f in _recording_frames(t)]
        name = f"stiff-{geometry}-{k}"
        sets.append(rc.frames_set(name, fr[:N_REF], fr[N_REF:], t.camera, mesh=MESH))
    return rc.RecordingProblem(sets)


def _firm_ratio(ev: rc.Evaluation) -> float:
    """Median |f_est| / |f_true| over frames with |f_true| >= 1 N (magnitudes: no rotation)."""
    truth = np.linalg.norm(ev.wrenches, axis=1)
    firm = truth >= 1.0
    assert firm.sum() >= 6
    return float(np.median(np.linalg.norm(ev.net_forces, axis=1)[firm] / truth[firm]))


def _calibrate_stiff(problem: rc.RecordingProblem, what: str) -> tuple[float, float, dict]:
    """(defaults' ratio, calibrated ratio, fitted parameters) with the default fit."""
    out = rc.calibrate_recordings(problem, max_evals=MAX_EVALS)  # the default fit
    fitted = out.result.params
    assert set(fitted) == set(rc.FIT_PARAMS) and out.rotation_fitted
    r0 = _firm_ratio(problem.evaluate(dict(cal.DEFAULTS)))
    r1 = _firm_ratio(out.final)
    print(
        f"{what}: median |f_est| / |f_true| (>= 1 N) {r0:.3f} with the defaults, {r1:.3f} "
        f"calibrated; fitted {fitted}, loss {out.result.initial_loss:.2f} -> "
        f"{out.result.loss:.2f}, rotation error {rc.rotation_angle_deg(out.rotation, R_TRUE):.1f} deg"
    )
    return r0, r1, fitted


def test_a_membrane_twice_as_stiff_is_read_at_its_force_scale(stiff):
    """Recordings of a membrane twice as stiff as the simulator's default (its pressure read
    right): the estimator reads a stiffer membrane's force partly from its deformation (a
    stiffer membrane dents wider), so the defaults read it low but within 20 % (measured 0.87
    with the nonlinear membrane; the linear one, whose E governed less, read 0.91), and
    `calibrate --recording`'s default fit (E, k_f, k_u, the ambient pressure and the F/T
    rotation) brings it within 10 % by raising E (measured 0.8 -> 2.0 MPa, ratio 1.00)."""
    assert stiff.gains.min() >= STIFF_FORCE_GAIN, stiff.gains
    r0, r1, fitted = _calibrate_stiff(_stiff_problem(stiff), f"membrane x{STIFF_FACTOR:g}")
    assert abs(r0 - 1.0) < 2 * STIFF_RATIO_TOL
    assert abs(r1 - 1.0) < STIFF_RATIO_TOL
    assert fitted["E"] > 1.5 * cal.DEFAULTS["E"]


def test_calibration_recovers_the_scale_of_a_bubble_twice_as_stiff_as_the_defaults(stiff):
    """Twice as stiff in both things that govern the force: the membrane's modulus doubled and
    its rest tension twice what its readings imply (readings lowered so that they say half the
    true rest gauge pressure, as a Punyo's do at a sea-level ambient). The defaults read the
    force clearly low; the default fit, the rotation unknown, brings it within 10 %, lowering the
    ambient pressure (raising the rest tension) to do it."""
    problem = _stiff_problem(stiff, shift_pa=101325.0 - SHIFTED_AMBIENT_PA)
    r0, r1, fitted = _calibrate_stiff(problem, "modulus x2, rest tension x2")
    assert r0 < STIFF_DEFAULT_BELOW
    assert abs(r1 - 1.0) < STIFF_RATIO_TOL
    assert fitted["ambient_pa"] < 101325.0 - 0.25 * (101325.0 - SHIFTED_AMBIENT_PA)
