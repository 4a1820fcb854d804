"""`bubble-rt estimate` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.cli import main
from bubble_rt.commands.estimate import parse_frames
from bubble_rt.frames import Frame
from bubble_rt.io.recordings import write_png_recording
from synth_rgbd import centre_dent, dome_depth, texture, warp


def test_parse_frames_ranges_and_lists():
    assert parse_frames("0-4", 20) == [0, 1, 2, 3, 4]
    assert parse_frames("3", 20) == [3]
    assert parse_frames("0-1, 5,7-8", 20) == [0, 1, 5, 7, 8]


def test_flow_choices_match_the_tracker():
    from bubble_rt.commands.estimate import FLOW_CHOICES
    from bubble_rt.estimation.deformation import FLOW_METHODS

    assert set(FLOW_CHOICES) == set(FLOW_METHODS) - {"oracle"}


def test_parse_frames_errors():
    with pytest.raises(ValueError, match="out of range"):
        parse_frames("18-20", 20)
    with pytest.raises(ValueError, match="empty frame range"):
        parse_frames("4-2", 20)
    with pytest.raises(ValueError, match="no frames"):
        parse_frames(" , ", 20)


DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


def test_estimate_command_on_png_fixture(tmp_path):
    cam = Camera.d405()
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    F = np.zeros((cam.height, cam.width, 2), np.float32)
    frames = [Frame(img, depth, 1e5, t=0.1 * i, wrench=np.zeros(6), index=i) for i in range(3)]
    frames.append(Frame(warp(img, F), depth, 1e5, t=0.3, wrench=np.ones(6), index=3))
    write_png_recording(tmp_path / "rec", frames, cam, depth_scale=1e-5)
    out = tmp_path / "out.json"
    args = [str(tmp_path / "rec"), "--reference-frames", "0-1", "--mesh", "coarse"]
    assert main(["estimate", *args, "--json", str(out), "--no-progress"]) == 0
    res = json.loads(out.read_text())
    assert [f["index"] for f in res["frames"]] == [0, 1, 2, 3]
    f = res["frames"][3]
    assert set(f) >= {"index", "t", "net_force", "contact_nodes", "valid_node_fraction"}
    assert set(f["timings_ms"]) >= {"flow", "lift", "solve", "post"}
    assert f["wrench"] == [1.0] * 6
    assert f["t"] == pytest.approx(0.3)
    assert res["mesh"]["nodes"] == 227
    for g in res["frames"]:  # untouched, identical frames: nothing to report
        assert g["contact_nodes"] == 0
        assert np.linalg.norm(g["net_force"]) < 0.05


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")
def test_estimate_command_real_recording(tmp_path):
    out = tmp_path / "real.json"
    args = [str(DATA), "--reference-frames", "0-4", "--mesh", "medium", "--frames", "5-19"]
    assert main(["estimate", *args, "--json", str(out), "--no-progress"]) == 0
    res = json.loads(out.read_text())
    frames = res["frames"]
    assert [f["index"] for f in frames] == list(range(5, 20))
    for f in frames:
        assert f["contact_nodes"] == 0
        assert np.linalg.norm(f["net_force"]) < 0.5
        assert len(f["wrench"]) == 6
        assert f["valid_node_fraction"] > 0.7


def _png_fixture(tmp_path: Path) -> Path:
    cam = Camera.d405()
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    frames = [Frame(img, depth, 1e5, t=0.1 * i, index=i) for i in range(3)]
    write_png_recording(tmp_path / "rec", frames, cam, depth_scale=1e-5)
    return tmp_path / "rec"


def test_estimate_takes_mesh_and_flow_from_config_and_flags_override_it(tmp_path):
    rec = _png_fixture(tmp_path)
    cfg = tmp_path / "c.toml"
    cfg.write_text('[estimator]\nmesh = "coarse"\nk_f = 0.2\n[flow]\nmethod = "dis_fast"\n')
    out = tmp_path / "out.json"
    base = ["estimate", str(rec), "--reference-frames", "0-1", "--no-progress", "--json", str(out)]
    assert main([*base, "--config", str(cfg)]) == 0
    res = json.loads(out.read_text())
    assert res["mesh"]["nodes"] == 227 and res["flow"]["method"] == "dis_fast"
    assert main([*base, "--config", str(cfg), "--flow", "farneback"]) == 0
    assert json.loads(out.read_text())["flow"]["method"] == "farneback"


def test_estimate_refuses_a_bad_config_naming_the_key(tmp_path, capsys):
    rec = _png_fixture(tmp_path)
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[estimator]\nk_f = -1.0\n")
    args = ["estimate", str(rec), "--config", str(cfg), "--json", str(tmp_path / "o.json")]
    assert main(args) == 2
    assert "invalid configuration: estimator.k_f" in capsys.readouterr().err


@pytest.mark.parametrize("content", [b"", b"not a mesh\n"], ids=["empty", "garbage"])
def test_estimate_refuses_an_unreadable_mesh_file_naming_the_option(tmp_path, capsys, content):
    """An empty mesh file ended the process inside meshio (SystemExit) without the key."""
    mesh = tmp_path / "m.vtk"
    mesh.write_bytes(content)
    out = tmp_path / "o.json"
    args = ["estimate", str(tmp_path / "none"), "--mesh", str(mesh), "--json", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"--mesh: cannot read mesh {mesh}" in err and not out.exists()
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[estimator]\nmesh = "{mesh}"\n')
    assert main(["estimate", str(tmp_path / "none"), "--config", str(cfg), "--json", str(out)]) == 2
    assert "estimator.mesh: cannot read mesh" in capsys.readouterr().err


def test_estimate_skips_the_bad_frames_of_an_mcap_recording(tmp_path):
    """The project's MCAP recordings go through the same tolerant iteration (estimate could
    not read them at all: it indexed frames, which an MCAP file does not offer)."""
    from daemon_fakes import coarse_mesh
    from recording_fakes import bad_mcap

    rec = tmp_path / "bad.mcap"
    bad_mcap(rec)  # frames 1-4 bad: image cut short, 16 x 12 rgb, all-NaN depth, NaN pressure
    coarse_mesh().save(tmp_path / "m.vtk")
    out = tmp_path / "o.json"
    args = ["estimate", str(rec), "--reference-frames", "0", "--mesh", str(tmp_path / "m.vtk")]
    assert main([*args, "--json", str(out), "--no-progress"]) == 0
    res = json.loads(out.read_text())
    assert [f["index"] for f in res["frames"]] == [0, 5, 6, 7]
    assert [(s["where"], s["kind"]) for s in res["skipped"]] == [
        ("bad.mcap frame 1", "colour"),
        ("bad.mcap frame 2", "frame"),
        ("bad.mcap frame 3", "depth"),
        ("bad.mcap frame 4", "pressure"),
    ]
    assert res["skipped_counts"] == {"colour": 1, "frame": 1, "depth": 1, "pressure": 1}


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")
def test_estimate_skips_a_truncated_file_of_a_real_punyo_recording(tmp_path):
    rec = tmp_path / "rec"
    (rec / "expand").mkdir(parents=True)
    for f in (DATA / "expand").iterdir():  # the real frames, one point cloud cut in half
        (rec / "expand" / f.name).symlink_to(f)
    (rec / "data.json").symlink_to(DATA / "data.json")
    cut = rec / "expand" / "pc_7.npy"
    cut.unlink()
    data = (DATA / "expand" / "pc_7.npy").read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    out = tmp_path / "o.json"
    args = [str(rec), "--reference-frames", "0-4", "--mesh", "coarse", "--frames", "5-9"]
    assert main(["estimate", *args, "--json", str(out), "--no-progress"]) == 0
    res = json.loads(out.read_text())
    assert [f["index"] for f in res["frames"]] == [5, 6, 8, 9]
    (skip,) = res["skipped"]
    assert skip["where"] == "rec frame 7" and skip["kind"] == "depth"
    assert "pc_7.npy: unreadable, damaged or truncated" in skip["reason"]
    for f in res["frames"]:  # untouched frames read about zero, as without the damage
        assert np.linalg.norm(f["net_force"]) < 0.5


def test_estimate_takes_an_mcap_recordings_own_reference_by_default(tmp_path):
    """A recording of this project holds the reference its daemon captured; a stream that
    starts in contact (the `punyo` scene does) has no untouched frames 0-4 to take."""
    from dataclasses import replace

    from sim_recordings import write_mcap

    cam = Camera.d405()
    depth = dome_depth(cam)
    img = texture(cam.height, cam.width)
    dent = centre_dent(cam, depth)
    untouched = Frame(img, depth, 1e5, wrench=np.zeros(6))
    pressed = Frame(img, dent, 1e5 + 300.0, wrench=np.zeros(6))
    rec = write_mcap(
        tmp_path / "r.mcap",
        [replace(pressed, index=i) for i in range(3)],
        [replace(untouched, index=i - 3) for i in range(3)],
        cam,
    )
    out = tmp_path / "o.json"
    base = ["estimate", str(rec), "--mesh", "coarse", "--no-progress", "--json", str(out)]
    assert main(base) == 0
    res = json.loads(out.read_text())
    assert res["reference_frames"] == [-3, -2, -1]
    assert all(np.linalg.norm(f["net_force"]) > 0.5 for f in res["frames"])
    # Frames named explicitly still win: the pressed frames as the reference read no force.
    assert main([*base, "--reference-frames", "0-1"]) == 0
    res = json.loads(out.read_text())
    assert res["reference_frames"] == [0, 1]
    assert all(np.linalg.norm(f["net_force"]) < 0.1 for f in res["frames"])
