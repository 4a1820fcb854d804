"""Issue 21, item 4 and the address part of item 7: a path that is not a regular file (FIFO,
device, folder) or a config too large to read whole is refused at once, naming the option, and
so is a port outside 1-65535. Each case runs the command in-process under a timeout, so a
regression (an open that blocks on a FIFO) fails instead of hanging CI."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from bubble_rt._validate import CONFIG_MAX_BYTES, PathError, regular_file
from bubble_rt.cli import main
from bubble_rt.config import DaemonConfig
from bubble_rt.io.recordings import PngRecording, open_recording, write_png_recording
from recording_fakes import png_frames

pytestmark = pytest.mark.timeout(20)


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    code = main(list(argv))
    return code, capsys.readouterr().err


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    p = tmp_path / "pipe.mcap"
    os.mkfifo(p)
    return p


@pytest.fixture
def fifo_toml(tmp_path: Path) -> Path:
    p = tmp_path / "pipe.toml"
    os.mkfifo(p)
    return p


def test_serve_config_fifo_is_refused(capsys, fifo_toml):
    code, err = _cli(capsys, "serve", "--config", str(fifo_toml), "--duration", "0.1")
    assert code == 2
    assert "--config" in err and "FIFO" in err and str(fifo_toml) in err


def test_config_check_fifo_is_refused(capsys, fifo_toml):
    code, err = _cli(capsys, "config", "check", str(fifo_toml))
    assert code == 2
    assert "config check FILE" in err and "FIFO" in err


def test_config_dev_zero_is_refused(capsys):
    code, err = _cli(capsys, "serve", "--config", "/dev/zero", "--duration", "0.1")
    assert code == 2
    assert "--config" in err and "character device" in err


def test_config_folder_is_refused(capsys, tmp_path):
    code, err = _cli(capsys, "config", "check", str(tmp_path))
    assert code == 2
    assert "folder" in err and str(tmp_path) in err


def test_config_too_large_is_refused(capsys, tmp_path):
    big = tmp_path / "big.toml"
    with open(big, "wb") as fh:  # sparse: no disk used
        fh.truncate(CONFIG_MAX_BYTES + 1)
    code, err = _cli(capsys, "config", "check", str(big))
    assert code == 2
    assert f"{CONFIG_MAX_BYTES}-byte limit" in err


def test_estimate_fifo_mcap_is_refused(capsys, fifo, tmp_path):
    code, err = _cli(capsys, "estimate", str(fifo), "--json", str(tmp_path / "out.json"))
    assert code == 2
    assert "FIFO" in err and str(fifo) in err
    assert not (tmp_path / "out.json").exists()


def test_serve_replay_fifo_mcap_is_refused(capsys, fifo):
    code, err = _cli(capsys, "serve", "--camera", f"replay:{fifo}", "--duration", "0.1")
    assert code == 2
    assert "--camera replay:" in err and "FIFO" in err


def test_estimate_json_output_fifo_is_refused(capsys, fifo_toml, tmp_path):
    frames, cam = png_frames(1, wrench=False)
    write_png_recording(tmp_path / "rec", frames, cam)
    code, err = _cli(capsys, "estimate", str(tmp_path / "rec"), "--json", str(fifo_toml))
    assert code == 2
    assert "--json" in err and "FIFO" in err


def test_serve_record_output_device_is_refused(capsys):
    code, err = _cli(capsys, "serve", "--record", "/dev/zero", "--duration", "0.1")
    assert code == 2
    assert "--record" in err and "character device" in err


def test_png_recording_with_a_fifo_frame_is_refused(tmp_path):
    frames, cam = png_frames(2, wrench=False)
    write_png_recording(tmp_path, frames, cam)
    (tmp_path / "depth_0001.png").unlink()
    os.mkfifo(tmp_path / "depth_0001.png")
    with pytest.raises(ValueError, match="FIFO"):
        open_recording(tmp_path)


@pytest.mark.parametrize("port", ["0", "99999"])
def test_pub_port_out_of_range_is_refused(capsys, port):
    code, err = _cli(capsys, "serve", "--pub", f"tcp://127.0.0.1:{port}", "--duration", "0.1")
    assert code == 2
    assert "--pub" in err and f"port {port} is outside 1-65535" in err


@pytest.mark.parametrize("port", ["0", "99999"])
def test_foxglove_port_out_of_range_is_refused(capsys, port):
    addr = f"ws://127.0.0.1:{port}"
    code, err = _cli(capsys, "serve", "--foxglove", addr, "--duration", "0.1")
    assert code == 2
    assert "--foxglove" in err and f"port {port} is outside 1-65535" in err


def test_config_pub_port_out_of_range_names_the_key():
    with pytest.raises(ValueError, match=r"pub.*port 70000 is outside 1-65535"):
        DaemonConfig.from_dict({"network": {"pub": "tcp://127.0.0.1:70000"}})
    # any free port and other transports stay valid
    DaemonConfig.from_dict({"network": {"pub": "tcp://127.0.0.1:*", "control": "ipc:///tmp/c"}})


def test_regular_files_and_symlinks_to_them_still_work(capsys, tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(DaemonConfig().to_toml())
    link = tmp_path / "link.toml"
    link.symlink_to(cfg)
    for p in (cfg, link):
        code, err = _cli(capsys, "config", "check", str(p))
        assert code == 0, err
        assert DaemonConfig.load(p) == DaemonConfig()
    frames, cam = png_frames(2, wrench=False)
    write_png_recording(tmp_path / "rec", frames, cam)
    (tmp_path / "rec" / "rgb_0001.png").rename(tmp_path / "rgb_elsewhere.png")
    (tmp_path / "rec" / "rgb_0001.png").symlink_to(tmp_path / "rgb_elsewhere.png")
    (tmp_path / "reclink").symlink_to(tmp_path / "rec")
    rec = open_recording(tmp_path / "reclink")
    assert isinstance(rec, PngRecording) and len(rec) == 2
    assert (rec[1].rgb == frames[1].rgb).all()


def test_symlink_to_a_fifo_is_refused(tmp_path, fifo):
    (tmp_path / "link").symlink_to(fifo)
    with pytest.raises(PathError, match="FIFO"):
        regular_file("--config", tmp_path / "link")


def test_simulate_scene_fifo_is_refused(capsys, fifo_toml, tmp_path):
    code, err = _cli(capsys, "simulate", str(fifo_toml), "-o", str(tmp_path / "o.npz"))
    assert code == 2
    assert "scene" in err and "FIFO" in err


def test_serve_sim_scene_device_is_refused(capsys):
    code, err = _cli(capsys, "serve", "--camera", "sim:/dev/zero", "--duration", "0.1")
    assert code == 2
    assert "--camera sim:" in err and "character device" in err


def test_bench_json_output_fifo_is_refused_before_the_run(capsys, fifo_toml):
    code, err = _cli(capsys, "bench", "--json", str(fifo_toml))
    assert code == 2
    assert "--json" in err and "FIFO" in err
