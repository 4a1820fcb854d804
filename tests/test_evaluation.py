"""Evaluation metrics on hand-made cases, aggregation, and the fan-out modes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.eval import (
    LIGHT_TOUCH_RANGE_N,
    UNTOUCHED_N,
    FanOut,
    aggregate,
    contact_iou,
    contact_normal,
    frame_metrics,
    lumped_areas,
    markdown_table,
    run_tasks,
    split_force_error,
    summarize,
    vertex_normals,
)
from bubble_rt.mesh import Mesh


def _square(x: float) -> float:
    return x * x


def test_iou_partial_overlap():
    est = np.array([1, 1, 0, 0], bool)
    gt = np.array([0, 1, 1, 0], bool)
    assert contact_iou(est, gt) == pytest.approx(1 / 3)


def test_iou_both_empty_is_undefined():
    z = np.zeros(5, bool)
    assert math.isnan(contact_iou(z, z))


def test_iou_estimate_only_scores_zero():
    assert contact_iou(np.array([1, 0, 0], bool), np.zeros(3, bool)) == 0.0


def test_iou_truth_only_scores_zero():
    assert contact_iou(np.zeros(3, bool), np.array([0, 1, 1], bool)) == 0.0


def test_iou_identical_is_one():
    m = np.array([0, 1, 1, 0, 1], bool)
    assert contact_iou(m, m) == 1.0


def test_iou_shape_mismatch_raises():
    with pytest.raises(ValueError, match="shape"):
        contact_iou(np.zeros(3, bool), np.zeros(4, bool))


def test_force_error_split_pure_normal():
    total, normal, shear = split_force_error(
        np.array([0.0, 0.0, -3.0]), np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, -1.0])
    )
    assert (total, normal, shear) == pytest.approx((2.0, 2.0, 0.0))


def test_force_error_split_pure_shear():
    total, normal, shear = split_force_error(
        np.array([1.0, 0.0, -2.0]), np.array([0.0, 0.0, -2.0]), np.array([0.0, 0.0, -1.0])
    )
    assert (total, normal, shear) == pytest.approx((1.0, 0.0, 1.0))


def test_force_error_split_is_pythagorean_on_tilted_normal():
    n = np.array([1.0, 0.0, -1.0]) / math.sqrt(2)
    total, normal, shear = split_force_error(np.array([3.0, 4.0, 0.0]), np.zeros(3), n)
    assert total == pytest.approx(5.0)
    assert normal == pytest.approx(3.0 / math.sqrt(2))
    assert normal**2 + shear**2 == pytest.approx(total**2)


def test_contact_normal_uses_truth_then_estimate_then_interior():
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    areas = np.ones(3)
    gt = np.array([True, False, False])
    est = np.array([False, True, False])
    assert contact_normal(normals, areas, gt, est) == pytest.approx([0, 0, -1])
    assert contact_normal(normals, areas, np.zeros(3, bool), est) == pytest.approx([-1, 0, 0])
    interior = np.array([False, False, True])
    got = contact_normal(normals, areas, np.zeros(3, bool), np.zeros(3, bool), interior)
    assert got == pytest.approx([0, -1, 0])


def test_dome_mean_normal_points_down():
    mesh = Mesh.preset("coarse")
    n = vertex_normals(mesh.vertices, mesh.triangles)
    a = lumped_areas(mesh.vertices, mesh.triangles)
    c = contact_normal(n, a, np.zeros(mesh.n_nodes, bool))
    assert c[2] < -0.9


def test_lumped_areas_sum_to_surface_area():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    a = lumped_areas(v, t)
    assert a.sum() == pytest.approx(1.0)
    assert a[0] == pytest.approx(1 / 3)


def _rec(geometry, estimator, f_est, f_gt, est, gt, **kw):
    n = len(gt)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    return frame_metrics(
        geometry=geometry,
        estimator=estimator,
        trajectory=0,
        frame=kw.get("frame", 0),
        f_est=np.asarray(f_est, float),
        f_gt=np.asarray(f_gt, float),
        est_contact=np.asarray(est, bool),
        gt_contact=np.asarray(gt, bool),
        normals=normals,
        areas=np.ones(n),
        truth_converged=kw.get("truth_converged", True),
    )


def test_unconverged_ground_truth_is_excluded_and_counted():
    # A physics step that failed gives no ground truth: its (huge) error must not count.
    recs = [
        _rec("point", "fem", [0, 0, -1], [0, 0, -1.5], [1, 0], [1, 0]),
        _rec("point", "fem", [0, 0, -1], [300, 400, 200], [1, 0], [1, 1], truth_converged=False),
    ]
    st = aggregate(recs)
    assert st["force_err_n"] == pytest.approx(0.5)
    assert st["miou"] == pytest.approx(1.0)
    assert st["n_frames"] == 1 and st["n_excluded"] == 1
    s = summarize(recs)
    assert s["average"]["fem"]["n_excluded"] == 1
    assert "(+1 excluded)" in markdown_table(s)


def test_aggregate_light_touch_and_false_contacts():
    recs = [
        # light touch detected
        _rec("round", "fem", [0, 0, -1], [0, 0, -1.0], [1, 0, 0], [1, 1, 0]),
        # light touch missed
        _rec("round", "fem", [0, 0, 0], [0, 0, -0.5], [0, 0, 0], [0, 1, 0]),
        # firm touch, not light
        _rec("round", "fem", [0, 0, -4], [0, 0, -5.0], [0, 1, 1], [0, 1, 1]),
        # untouched, false contact on two nodes
        _rec("round", "fem", [0, 0, -0.2], [0, 0, 0], [1, 1, 0], [0, 0, 0]),
        # untouched, quiet (undefined IoU, left out of mIoU)
        _rec("round", "fem", [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]),
    ]
    st = aggregate(recs)
    assert st["light_touch_rate"] == pytest.approx(0.5)
    assert st["false_contact_rate"] == pytest.approx(0.5)
    assert st["false_nodes"] == pytest.approx(1.0)
    assert (st["n_light"], st["n_untouched"]) == (2, 2)
    # IoUs 0.5, 0, 1, 0 -> mean 0.375 (the all-empty frame is excluded)
    assert st["miou"] == pytest.approx(0.375)
    assert st["force_err_n"] == pytest.approx((0 + 0.5 + 1 + 0.2 + 0) / 5)
    assert st["force_err_contact_n"] == pytest.approx(1.5 / 3)


def test_touch_between_truth_nodes_is_a_light_touch_not_a_false_contact():
    """An indenter pressing 0.5 N between estimator nodes leaves the truth's node mask empty:
    marking contact there detects a touch, it is no false contact."""
    st = aggregate([_rec("point", "fem", [0, 0, -0.45], [0, 0, -0.5], [1, 0, 0], [0, 0, 0])])
    assert st["light_touch_rate"] == 1.0 and st["n_light"] == 1
    assert st["n_untouched"] == 0 and math.isnan(st["false_contact_rate"])
    assert st["force_err_contact_n"] == pytest.approx(0.05)


def test_false_contacts_count_only_frames_under_the_untouched_threshold():
    below = 0.9 * UNTOUCHED_N
    recs = [
        # truly untouched (a residual force under the threshold), contact marked: false
        _rec("round", "fem", [0, 0, -0.1], [0, 0, -below], [1, 1, 1], [0, 0, 0]),
        # truly untouched, nothing marked
        _rec("round", "fem", [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]),
        # exactly at the threshold: touched, neither untouched nor (under 0.1 N) light
        _rec("round", "fem", [0, 0, -0.1], [0, 0, -UNTOUCHED_N], [1, 0, 0], [0, 0, 0]),
    ]
    st = aggregate(recs)
    assert st["n_untouched"] == 2 and st["false_contact_rate"] == pytest.approx(0.5)
    assert st["false_nodes"] == pytest.approx(1.5)  # (3 + 0) contact nodes over 2 frames
    assert st["n_light"] == 0 and math.isnan(st["light_touch_rate"])


def test_light_touch_range_is_inclusive_and_ignores_the_truth_mask():
    lo, hi = LIGHT_TOUCH_RANGE_N
    marked, quiet = [1, 0], [0, 0]
    recs = [
        _rec("line", "fem", [0, 0, -lo], [0, 0, -lo], marked, quiet),  # in (bound), detected
        _rec("line", "fem", [0, 0, -hi], [0, 0, -hi], quiet, [1, 1]),  # in (bound), missed
        _rec("line", "fem", [0, 0, -1], [0, 0, -0.99 * lo], marked, quiet),  # below the range
        _rec("line", "fem", [0, 0, -2], [0, 0, -1.01 * hi], quiet, [1, 1]),  # above the range
        _rec("line", "fem", [0, 0, -1], [0.6, 0.0, -0.8], marked, quiet),  # |f| = 1 N, tilted
    ]
    st = aggregate(recs)
    assert st["n_light"] == 3
    assert st["light_touch_rate"] == pytest.approx(2 / 3)


def test_average_pools_light_and_untouched_frames_over_indenters():
    recs = [
        # round: 1 light touch, detected; 1 untouched frame, quiet
        _rec("round", "fem", [0, 0, -1], [0, 0, -1], [1, 0], [1, 0]),
        _rec("round", "fem", [0, 0, 0], [0, 0, 0], [0, 0], [0, 0], frame=1),
        # point: 3 light touches, 1 detected; 3 untouched frames, 1 with contact
        *[
            _rec("point", "fem", [0, 0, -1], [0, 0, -1], [k == 0, 0], [1, 0], frame=k)
            for k in range(3)
        ],
        *[
            _rec("point", "fem", [0, 0, 0], [0, 0, 0], [k == 0, 0], [0, 0], frame=3 + k)
            for k in range(3)
        ],
    ]
    av = summarize(recs)["average"]["fem"]
    # (1 + 1) of 4 light frames (not the indenters' mean (1 + 1/3) / 2); 1 of 4 untouched
    assert av["light_touch_rate"] == pytest.approx(0.5)
    assert av["false_contact_rate"] == pytest.approx(0.25)
    assert av["false_nodes"] == pytest.approx(0.25)
    assert (av["n_light"], av["n_untouched"], av["n_frames"]) == (4, 4, 8)


def test_table_and_summary_state_the_thresholds_and_frame_counts():
    recs = [
        _rec("round", "fem", [0, 0, -1], [0, 0, -1], [1, 0], [1, 0]),
        _rec("round", "fem", [0, 0, 0], [0, 0, 0], [0, 0], [0, 0], frame=1),
        _rec("round", "fem", [0, 0, -3], [0, 0, -3], [1, 0], [1, 0], frame=2),
    ]
    s = summarize(recs)
    assert s["thresholds"] == {
        "untouched_below_n": UNTOUCHED_N,
        "light_touch_n": list(LIGHT_TOUCH_RANGE_N),
    }
    table = markdown_table(s)
    assert f"false contact (< {UNTOUCHED_N:g} N)" in table
    assert "light det. (0.1-1.5 N)" in table
    # frames, light, untouched
    assert "| round |" in table and table.split("| round |")[1].split("\n")[0].endswith(
        "| 3 | 1 | 1 |"
    )


def test_aggregate_without_light_touches_is_nan():
    st = aggregate([_rec("round", "fem", [0, 0, -4], [0, 0, -5.0], [1], [1])])
    assert math.isnan(st["light_touch_rate"])
    assert math.isnan(st["false_contact_rate"])
    assert st["n_light"] == 0 and st["n_untouched"] == 0


def test_summarize_keys_and_unweighted_average():
    recs = [
        _rec("round", "fem", [0, 0, -2], [0, 0, -1], [1, 0], [1, 0]),
        _rec("point", "fem", [0, 0, -4], [0, 0, -1], [1, 0], [1, 1]),
        _rec("point", "fem", [0, 0, -4], [0, 0, -1], [1, 0], [1, 1], frame=1),
        _rec("round", "frictionless", [0, 0, -1], [0, 0, -1], [1, 0], [1, 0]),
    ]
    s = summarize(recs)
    assert list(s["geometries"]) == ["round", "point"]
    for key in ("miou", "force_err_n", "normal_err_n", "shear_err_n"):
        assert key in s["geometries"]["round"]["fem"]
        assert key in s["average"]["fem"]
    assert s["average"]["fem"]["force_err_n"] == pytest.approx((1 + 3) / 2)
    assert s["average"]["fem"]["miou"] == pytest.approx((1 + 0.5) / 2)
    assert "frictionless" not in s["geometries"]["point"]
    table = markdown_table(s)
    assert "| average |" in table
    assert "fem mIoU" in table and "frictionless force err (N)" in table


def test_fanout_processes_match_inline():
    tasks = [1.0, 2.0, 3.0, 4.0, 5.0]
    with FanOut(workers=2) as fan:
        assert fan.map(_square, tasks) == [1.0, 4.0, 9.0, 16.0, 25.0]
    assert run_tasks(_square, tasks, workers=1) == [1.0, 4.0, 9.0, 16.0, 25.0]


def test_fanout_dask_local_cluster_matches_processes():
    distributed = pytest.importorskip("distributed")
    tasks = [0.5 * k for k in range(7)]
    expected = run_tasks(_square, tasks, workers=2)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        got = run_tasks(_square, tasks, scheduler=cluster.scheduler_address)
    assert got == expected


def test_eval_command_end_to_end_on_a_tiny_dataset(tmp_path):
    """Simulate one short trajectory per indenter pair, run both estimators, write JSON/figures."""
    import json

    from bubble_rt.cli import main

    out = tmp_path / "eval.json"
    figs = tmp_path / "figs"
    rc = main(
        [
            "eval",
            "--geometries",
            "round,point",
            "--trajectories",
            "1",
            "--frames",
            "6",
            "--mesh",
            "coarse",
            "--workers",
            "1",
            "--no-progress",
            "--json",
            str(out),
            "--figures",
            str(figs),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    for g in ("round", "point"):
        for e in ("fem", "frictionless"):
            st = doc["geometries"][g][e]
            assert {"miou", "force_err_n", "normal_err_n", "shear_err_n"} <= set(st)
            assert st["n_frames"] == 6
            assert st["force_err_n"] is not None and st["force_err_n"] >= 0
    for e in ("fem", "frictionless"):
        assert {"miou", "force_err_n", "normal_err_n", "shear_err_n"} <= set(doc["average"][e])
    assert doc["throughput"]["frames"] == 12
    assert doc["thresholds"]["untouched_below_n"] == UNTOUCHED_N
    assert (figs / "net_force_round.png").stat().st_size > 0
    assert (figs / "contact_point.png").stat().st_size > 0


def test_eval_trajectory_same_on_dask_as_inline():
    distributed = pytest.importorskip("distributed")
    from bubble_rt.eval import evaluate_trajectory, make_tasks

    tasks = make_tasks(["round"], 1, 4, mesh="coarse", estimators=("fem",))
    inline = run_tasks(evaluate_trajectory, tasks)
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        remote = run_tasks(evaluate_trajectory, tasks, scheduler=cluster.scheduler_address)
    a = [r.force_err_n for r in inline[0].records]
    b = [r.force_err_n for r in remote[0].records]
    assert len(a) == 4
    assert b == pytest.approx(a, abs=1e-9)


DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


@pytest.mark.skipif(not DATA.exists(), reason="shared real data not present")
def test_recording_eval_on_untouched_real_frames():
    from bubble_rt.eval import evaluate_recording, recording_table

    res = evaluate_recording(DATA, estimators=("fem",), n_reference=5, max_frames=12)
    assert res["frames"] == 7
    assert res["touched_frames"] == 0
    st = res["estimators"]["fem"]
    # untouched sensor: the product reports (almost) no force and no contact
    assert st["force_mag_err_n"] < 1.5
    assert st["false_contact_rate"] is not None and st["false_contact_rate"] <= 0.5
    assert "| fem |" in recording_table(res)


def test_recording_eval_takes_an_mcap_recordings_own_reference_and_its_wrench_bias(tmp_path):
    """A recording of this project holds the untouched reference its daemon captured, with
    their wrenches: that is the reference and the wrench bias, and every stream frame is
    scored, also when the stream starts in contact (as calibrate and estimate read it)."""
    from dataclasses import replace

    from bubble_rt.camera import Camera
    from bubble_rt.eval import evaluate_recording, recording_table
    from bubble_rt.frames import Frame
    from sim_recordings import write_mcap
    from synth_rgbd import centre_dent, dome_depth, texture

    cam = Camera.d405()
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    dent = centre_dent(cam, depth)
    bias = np.array([0.4, -0.3, 0.2, 0.0, 0.0, 0.0])
    press = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])
    untouched = Frame(img, depth, 1e5, wrench=bias)
    pressed = Frame(img, dent, 1e5 + 300.0, wrench=bias + press)
    rec = write_mcap(
        tmp_path / "r.mcap",
        [replace(pressed, index=i) for i in range(3)],
        [replace(untouched, index=i - 3) for i in range(3)],
        cam,
    )
    res = evaluate_recording(rec, estimators=("fem",), mesh="coarse", n_reference=5)
    assert (res["reference"], res["reference_frames"], res["frames"]) == ("recorded", 3, 3)
    # every frame pressed 2 N over the reference's bias: all touched (the first frames as the
    # reference would have read 0 N and scored one frame)
    assert res["touched_frames"] == 3
    st = res["estimators"]["fem"]
    assert st["recall"] == 1.0
    assert st["mean_force_n"] > 0.5
    assert "the reference is the 3 frames the recording holds" in recording_table(res)


def test_eval_seed_changes_the_simulated_trajectories():
    """`eval --seed N` draws other trajectories: the scene a seed gives differs from the default."""
    import argparse

    from bubble_rt.commands import eval as eval_cmd
    from bubble_rt.eval import EVAL_SEED_BASE, make_tasks, trajectory_scene

    p = argparse.ArgumentParser()
    eval_cmd.add_arguments(p)
    assert p.parse_args(["--seed", "7"]).seed == 7
    assert p.parse_args([]).seed is None
    assert {t.seed for t in make_tasks(["round"], 2, 4, seed_base=7)} == {7}
    a = trajectory_scene("round", 0, 6, EVAL_SEED_BASE)
    b = trajectory_scene("round", 0, 6, 7)
    assert a.name == b.name
    assert a != b


@pytest.mark.parametrize("command", ["eval", "bench"])
def test_eval_and_bench_refuse_a_bad_config_naming_the_key(tmp_path, capsys, command):
    from bubble_rt.cli import main

    cfg = tmp_path / "bad.toml"
    cfg.write_text("[estimator]\nk_u = 1.0\nwhat = 3\n")
    assert main([command, "--config", str(cfg)]) == 2
    assert "invalid configuration: estimator.what" in capsys.readouterr().err


def test_config_overrides_come_through_the_daemon_loader(tmp_path):
    from bubble_rt.eval import load_config_overrides

    cfg = tmp_path / "c.toml"
    cfg.write_text("[estimator]\nk_f = 0.25\nyoungs_modulus = 2e6\n")
    assert load_config_overrides(cfg) == {"k_f": 0.25, "E": 2e6}


def test_every_estimator_key_of_a_config_reaches_the_evaluated_estimator(tmp_path):
    # eval and bench used to keep six named keys and drop the others (support_tol,
    # nonlinear_iterations, ...) without a word.
    from bubble_rt.estimation.estimator import CONFIG_KEYS, EstimatorConfig
    from bubble_rt.eval import load_config_overrides
    from bubble_rt.eval.tasks import estimator_config

    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[estimator]\nsupport_tol = 0.3\nnonlinear_iterations = 0\nthickness = 1e-3\n"
        "peak_radius_m = 0.004\n"
    )
    got = estimator_config(load_config_overrides(cfg))
    default = EstimatorConfig()
    assert (got.support_tol, got.nonlinear_iterations) == (0.3, 0)
    assert (got.material.thickness, got.peak_radius_m) == (1e-3, 0.004)
    assert got.material.E == default.material.E and got.k_f == default.k_f
    assert {"support_tol", "nonlinear_iterations", "thickness"} <= set(CONFIG_KEYS)


def _patch(centroid_mm, force, pressure_centroid_mm=None, area_cm2=float("nan")):
    from types import SimpleNamespace

    c = np.asarray(centroid_mm, float) / 1e3
    pc = c if pressure_centroid_mm is None else np.asarray(pressure_centroid_mm, float) / 1e3
    return SimpleNamespace(
        centroid=c, pressure_centroid=pc, force=np.asarray(force, float), area=area_cm2 / 1e4
    )


def test_patch_area_is_scored_against_the_matched_true_patch():
    from bubble_rt.eval.metrics import patch_scores

    truth = [
        _patch([-12.5, 0, 30], [0, 0, -2.0], area_cm2=0.5),
        _patch([12.5, 0, 30], [0, 0, -3.0], area_cm2=1.0),
    ]
    # listed in the other order: each is scored against the true patch it is nearest to
    est = [
        _patch([-13, 0, 30], [0, 0, -2.0], area_cm2=1.5),
        _patch([13, 0, 30], [0, 0, -3.0], area_cm2=0.8),
    ]
    assert patch_scores(est, truth).area_ratio == pytest.approx([0.8, 3.0])
    # a true patch with no area (or no match) is not scored
    assert patch_scores(est[:1], truth).area_ratio == pytest.approx([1.5 / 1.0])
    assert patch_scores(est, [_patch([0, 0, 30], [0, 0, -3.0])]).area_ratio == []


def test_patch_scores_match_centroids_and_find_two_contacts():
    from bubble_rt.eval.metrics import patch_scores

    truth = [_patch([-12.5, 0, 30], [0, 0, -2.0]), _patch([12.5, 0, 30], [0, 0, -3.0])]
    est = [_patch([13, 0, 30], [0, 0, -3.3], [12.5, 1, 30]), _patch([-14, 0, 30], [0, 0, -1.7])]
    s = patch_scores(est, truth)
    # The larger true patch first: matched to the nearer estimate.
    assert s.centroid_err_mm == pytest.approx([0.5, 1.5])
    assert s.pressure_centroid_err_mm == pytest.approx([1.0, 1.5])
    assert s.two_contact and s.two_found
    # One patch force off by 25 %: not found; a third estimated patch: not found either.
    assert not patch_scores([est[0], _patch([-14, 0, 30], [0, 0, -1.5])], truth).two_found
    assert not patch_scores([*est, _patch([0, 0, 35], [0, 0, -0.1])], truth).two_found
    # One estimated patch for two true ones: the second is missed (NaN).
    one = patch_scores(est[:1], truth)
    assert not one.two_found and math.isnan(one.centroid_err_mm[1])
    # A true patch below PATCH_MIN_N is not scored and makes no two-contact frame.
    weak = patch_scores(est, [truth[1], _patch([-12.5, 0, 30], [0, 0, -0.2])])
    assert len(weak.centroid_err_mm) == 1 and not weak.two_contact


def test_wrench_stats_over_frames_of_one_newton_or_more():
    from dataclasses import replace

    from bubble_rt.eval.metrics import wrench_stats

    base = _rec("split", "fem", [0, 0, -2], [0, 0, -2], [1, 0], [1, 0])
    recs = [
        replace(
            base,
            tau_est=[0.011, 0, 0],
            tau_gt=[0.01, 0, 0],
            centroid_err_mm=[1.0, 3.0],
            pressure_centroid_err_mm=[0.5, 1.0],
            patch_area_ratio=[0.5, 1.1],
            two_contact=True,
            two_found=True,
        ),
        replace(
            base,
            tau_est=[0, 0.013, 0],
            tau_gt=[0, 0.01, 0],
            centroid_err_mm=[float("nan")],
            pressure_centroid_err_mm=[float("nan")],
            two_contact=True,
        ),
        replace(base, tau_est=[0, 0, 0.02], tau_gt=[0, 0, 0.01], patch_area_ratio=[2.0]),
        # under 1 N: not scored however wrong
        replace(
            base,
            f_gt=[0, 0, -0.5],
            tau_est=[1, 1, 1],
            tau_gt=[0, 0, 0.001],
            centroid_err_mm=[50.0],
            patch_area_ratio=[9.0],
            two_contact=True,
        ),
    ]
    st = wrench_stats(recs)
    assert st["n_wrench"] == 3 and st["n_torque"] == 3
    assert st["torque_rel_err"] == pytest.approx(0.3)  # median of 0.1, 0.3, 1.0
    assert st["torque_lever_err_mm"] == pytest.approx(1.5)  # median of 0.5, 1.5, 5 mm (2 N)
    assert st["centroid_err_mm"] == pytest.approx(2.0)  # median of 1, 3 (the miss is counted apart)
    assert st["n_patches_scored"] == 3 and st["n_patches_missed"] == 1
    assert st["centroid_within_tol"] == pytest.approx(1 / 3)
    assert st["pressure_centroid_within_tol"] == pytest.approx(2 / 3)
    assert st["two_contact_rate"] == pytest.approx(0.5) and st["n_two_contact"] == 2
    assert st["patch_area_ratio"] == pytest.approx(1.1)  # median of 0.5, 1.1, 2.0 (not 9)
    assert st["patch_area_rel_err"] == pytest.approx(0.5)  # median of 0.5, 0.1, 1.0
    s = summarize(recs)
    assert s["average"]["fem"]["torque_rel_err"] == pytest.approx(0.3)
    assert "two contacts found" in markdown_table(s)
    assert "patch area / truth" in markdown_table(s)


def test_eval_recording_reports_an_unreadable_recording_instead_of_a_traceback(tmp_path, capsys):
    """A missing recording and one without a wrench are refused with exit code 2 and a
    message that says what is wrong (they raised a traceback)."""
    from bubble_rt.camera import Camera
    from bubble_rt.cli import main
    from bubble_rt.frames import Frame
    from bubble_rt.io.recordings import write_png_recording
    from synth_rgbd import dome_depth, texture

    missing = tmp_path / "missing"
    assert main(["eval", "--recording", str(missing), "--no-progress"]) == 2
    assert f"bubble-rt eval: recording folder not found: {missing}" in capsys.readouterr().err
    cam = Camera.d405()
    frame = Frame(texture(cam.height, cam.width), dome_depth(cam), 1e5)
    folder = write_png_recording(tmp_path / "nowrench", [frame] * 3, cam)
    assert main(["eval", "--recording", str(folder), "--mesh", "coarse", "--no-progress"]) == 2
    assert "frames without a wrench" in capsys.readouterr().err
