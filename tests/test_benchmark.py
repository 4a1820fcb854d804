"""Benchmark suite: Pareto front logic and the JSON layout of a tiny run (no timing asserts)."""

from __future__ import annotations

import json
import math

import pytest
from bubble_rt.eval.benchmark import pareto_front


def _pt(t, e, m):
    return {"time_ms": t, "force_err_n": e, "miou": m}


def test_pareto_drops_dominated_point():
    pts = [_pt(1.0, 2.0, 0.5), _pt(2.0, 2.5, 0.4), _pt(3.0, 1.0, 0.5)]
    assert pareto_front(pts) == [0, 2]


def test_pareto_keeps_tradeoff_on_miou():
    pts = [_pt(1.0, 1.0, 0.3), _pt(1.0, 1.0, 0.6)]
    assert pareto_front(pts) == [1]


def test_pareto_identical_points_both_kept():
    pts = [_pt(1.0, 1.0, 0.5), _pt(1.0, 1.0, 0.5)]
    assert pareto_front(pts) == [0, 1]


def test_pareto_nan_miou_counts_as_worst():
    pts = [_pt(1.0, 1.0, math.nan), _pt(1.0, 1.0, 0.1)]
    assert pareto_front(pts) == [1]


def test_bench_tiny_run_json_keys(tmp_path):
    from bubble_rt.cli import main

    out = tmp_path / "bench.json"
    plot = tmp_path / "pareto.png"
    rc = main(
        [
            "bench",
            "--quick",
            "--frames",
            "2",
            "--reference-frames",
            "1",
            "--json",
            str(out),
            "--plot",
            str(plot),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    for name, nodes in (("coarse", 227), ("medium", 390), ("fine", 749)):
        m = doc["meshes"][name]
        assert m["nodes"] == nodes
        assert m["hz"] > 0
        assert m["latency_ms"]["p50"] > 0 and m["latency_ms"]["p99"] >= m["latency_ms"]["p50"]
        assert {"flow", "lift", "solve", "post"} <= set(m["stages_ms"])
        assert "reference_ms" in m and "speedup" in m
    med = doc["meshes"]["medium"]
    assert med["reference_ms"] > 0 and med["speedup"] > 0
    assert med["reference"]["net_force_diff_n"] >= 0
    assert len(doc["sweep"]) >= 3
    assert sum(p["default"] for p in doc["sweep"]) == 1
    assert any(p["pareto"] for p in doc["sweep"])
    for p in doc["sweep"]:
        assert {"time_ms", "force_err_n", "miou", "mesh", "flow", "solver_tol"} <= set(p)
    assert plot.stat().st_size > 0


@pytest.mark.parametrize("key", ["hz", "speedup"])
def test_bench_table_renders_missing_values(key):
    from bubble_rt.eval.benchmark import mesh_table

    res = {
        "meshes": {
            "coarse": {
                "nodes": 227,
                "flows": {
                    "dis_medium": {
                        "hz": float("nan") if key == "hz" else 10.0,
                        "latency_ms": {"p50": 100.0, "p99": 120.0},
                        "stages_ms": {"flow": 1.0},
                        "iterations": 5.0,
                        "force_err_n": 1.0,
                        "miou": 0.5,
                    }
                },
                "reference_ms": None,
                "speedup": None,
            }
        }
    }
    table = mesh_table(res)
    assert "| coarse | 227 | dis_medium |" in table
    assert table.count("\n") == 2
