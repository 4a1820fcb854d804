"""`bubble-rt serve` process behaviour: SIGINT / SIGTERM shut down cleanly, recording finalised."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
from bubble_rt.daemon.service import Daemon
from bubble_rt.io.client import ControlError, Controller, Subscriber
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    refused_at_load,
)
from recording_fakes import make_punyo
from waiting import ANY_PORT, ServedProcess, child_env, wait_for

pytestmark = pytest.mark.timeout(90)
TESTS = Path(__file__).resolve().parent


def _run_and_signal(sig: int, tmp_path: Path) -> tuple[int, Path, str]:
    rec = tmp_path / "run.mcap"
    served = ServedProcess(
        [sys.executable, str(TESTS / "daemon_fakes.py")]
        + ["--pub", ANY_PORT, "--control", ANY_PORT, "--record", str(rec)],
        env=child_env(),
    )
    try:
        pub, ctl = served.addresses(30)
        with Subscriber(pub, ctl, timeout_s=30) as sub:
            got = list(sub.frames(count=10, timeout_s=30))
        assert len(got) == 10
        served.proc.send_signal(sig)
        # The issue asked for a clean shutdown within 2 s of the signal: measured by
        # bench/daemon_bench.py (shutdown_s); here the state: it exits, cleanly, by itself.
        returncode = served.finish(30)
    finally:
        served.kill()
    return returncode, rec, served.err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_signal_shuts_down_and_finalises_recording(sig, tmp_path):
    from mcap.reader import make_reader

    returncode, rec, err = _run_and_signal(sig, tmp_path)
    assert returncode == 0, err
    assert "recording finalised" in err
    with open(rec, "rb") as f:
        summary = make_reader(f).get_summary()  # needs the footer written by finish()
    assert summary is not None
    topics = {c.topic for c in summary.channels.values()}
    assert {"/bubble_rt/force", "/bubble_rt/rgb", "/bubble_rt/mesh"} <= topics


def test_serve_rejects_invalid_config_naming_the_key(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[estimator]\nk_f = -1.0\n")
    out = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "serve", "--config", str(cfg)],
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "estimator.k_f" in out.stderr


def test_serve_realsense_without_package_is_a_clear_error(tmp_path):
    code = (
        "import sys; sys.modules['pyrealsense2'] = None\n"
        "from bubble_rt.cli import main\n"
        f"sys.exit(main(['serve', '--camera', 'realsense', '--pub', '{ANY_PORT}',"
        f" '--control', '{ANY_PORT}']))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=child_env(), capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 1
    assert "pyrealsense2" in out.stderr and "pip install" in out.stderr


@pytest.mark.timeout(240)
def test_cli_flags_are_checked_like_the_file(capsys):
    from bubble_rt.cli import main

    assert main(["serve", "--sensor-id", "a b", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "sensor_id" in err and "'a b'" in err
    assert main(["serve", "--mesh", "/nonexistent/mesh.vtk", "--duration", "0.1"]) == 2
    assert "estimator.mesh" in capsys.readouterr().err


@pytest.mark.timeout(240)
def test_mesh_that_is_not_a_mesh_stops_the_start(tmp_path):
    bad = tmp_path / "hostname"
    bad.write_text("myhost\n")
    pub, ctl = ANY_PORT, ANY_PORT
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "serve", "--mesh", str(bad)]
        + ["--pub", pub, "--control", ctl, "--duration", "5"],
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert "estimator.mesh" in proc.stderr and str(bad) in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.timeout(240)
def test_huge_reference_frame_count_is_refused_and_sigint_before_ready_exits_cleanly(tmp_path):
    e = refused_at_load("reference.frames", 1000000000)
    assert e.key == "reference.frames" and "[1, 300]" in str(e)
    # The largest accepted count on the real simulated scene: never ready within the test,
    # then SIGINT: a clean exit, no std::terminate, no traceback.
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[reference]\nframes = 300\n[network]\npub = "{ANY_PORT}"\ncontrol = "{ANY_PORT}"\n'
        "[estimator]\nmesh = 'coarse'\n"
    )
    served = ServedProcess(
        [sys.executable, "-m", "bubble_rt", "serve", "--config", str(cfg)], env=child_env()
    )
    try:
        _, ctl = served.addresses(60)
        with Controller(ctl, timeout_s=30) as c:
            st = c.status()
            assert st.state == "starting" and "capturing reference" in st.reason

            # SIGINT while the capture is under way: the camera has delivered frames.
            def camera_delivers() -> bool:
                sources = c.status().sources
                return any(v["received"] > 0 for k, v in sources.items() if k.startswith("sim"))

            assert wait_for(camera_delivers, 60)
        served.proc.send_signal(signal.SIGINT)
        returncode = served.finish(20)
    finally:
        served.kill()
    err = served.err
    assert returncode == 0, err
    assert "terminate called" not in err and "Traceback" not in err


@pytest.mark.timeout(240)
def test_recording_path_under_an_existing_file_is_a_clear_error(tmp_path):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    pub, ctl = ANY_PORT, ANY_PORT
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "serve", "--record", str(a_file / "run.mcap")]
        + ["--pub", pub, "--control", ctl, "--duration", "5"],
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert f"{a_file} is a file, not a folder" in proc.stderr
    assert "recording.path" in proc.stderr  # the key, like every configuration error
    assert "Traceback" not in proc.stderr and "FileExistsError" not in proc.stderr
    # record_start without a path, [recording] directory under a file: a refusal, no traceback
    cfg = fake_config(**{"recording.directory": str(a_file / "sub")})
    d = Daemon(
        cfg, camera=ScriptedCamera(), pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    try:
        assert d.wait_ready(20)
        with Controller(d.control_address) as c:
            with pytest.raises(ControlError, match="is \\(or is under\\) a file, not a folder"):
                c.record_start()
            assert c.status().state in ("starting", "running", "degraded")
    finally:
        d.stop()


@pytest.mark.timeout(120)
def test_serve_refuses_to_record_over_an_existing_file(tmp_path, capsys):
    from bubble_rt.cli import main

    root = tmp_path / "rec"
    make_punyo(root, n=3)
    keep = tmp_path / "run.mcap"
    keep.write_text("an earlier run\n")
    net = ["--pub", ANY_PORT, "--control", ANY_PORT]
    args = ["serve", "--camera", f"replay:{root}", "--record", str(keep), "--duration", "0.1"]
    assert main(args + net) == 1
    assert "file exists" in capsys.readouterr().err and keep.read_text() == "an earlier run\n"
