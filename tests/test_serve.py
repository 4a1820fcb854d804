"""`bubble-rt serve` process behaviour: SIGINT / SIGTERM shut down cleanly, recording finalised."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from bubble_rt.io.client import Subscriber
from waiting import ANY_PORT, ServedProcess

pytestmark = pytest.mark.timeout(90)
TESTS = Path(__file__).resolve().parent


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS)] + [p for p in sys.path if p])
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def _run_and_signal(sig: int, tmp_path: Path) -> tuple[int, Path, str]:
    rec = tmp_path / "run.mcap"
    served = ServedProcess(
        [sys.executable, str(TESTS / "daemon_fakes.py")]
        + ["--pub", ANY_PORT, "--control", ANY_PORT, "--record", str(rec)],
        env=_env(),
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
        env=_env(),
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
        [sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 1
    assert "pyrealsense2" in out.stderr and "pip install" in out.stderr
