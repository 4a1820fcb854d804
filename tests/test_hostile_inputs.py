"""Issue 14: bad configuration refused at load (key, value and range named), start-up failures
exit non-zero, a failing source is degraded and counted, clean exits, replays that reproduce
the live run. One named test per case of the issue, plus a configuration fuzz test."""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bubble_rt.config import (
    ConfigError,
    DaemonConfig,
    dump_toml,
    key_choices,
    key_comment,
    key_range,
    keys,
)
from bubble_rt.daemon.service import Daemon
from bubble_rt.io.client import ControlError, Controller, Subscriber
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    status_of,
)
from waiting import ANY_PORT, ServedProcess, nobody_listens, wait_for

pytestmark = pytest.mark.timeout(240)
TESTS = Path(__file__).resolve().parent


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS)] + [p for p in sys.path if p])
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def _nest(dotted: str, value: Any) -> dict[str, Any]:
    section, _, name = dotted.rpartition(".")
    return {section: {name: value}} if section else {name: value}


def _err(dotted: str, value: Any) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        DaemonConfig.from_dict(_nest(dotted, value))
    return ei.value


# ------------------------------------------------------------------------------ fuzz
HUGE_INT = 10**12
FUZZ_VALUES: list[Any] = [
    "wrong type",
    True,
    math.nan,
    math.inf,
    -math.inf,
    -1,
    -1.0,
    0,
    0.0,
    1e300,
    -1e300,
    HUGE_INT,
    5e-324,
]


#: Checks between keys (the other key keeps its default).
CROSS_CHECKS = {
    "pressure.min_pa": lambda v: v < DaemonConfig().pressure.max_pa,
    "pressure.max_pa": lambda v: v > DaemonConfig().pressure.min_pa,
}


def _expected_valid(f: Any, value: Any, dotted: str = "") -> bool | None:
    """What the fuzz test expects of ``value`` for key ``dotted`` (from its declaration)."""
    default = f.default
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, str):
        # Numbers are the wrong type; words: only the declared choices (free-form words such
        # as paths and sources have their own named tests).
        if not isinstance(value, str):
            return False
        choices = key_choices(f)
        return None if choices is None else value in choices
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if isinstance(default, int) and not isinstance(value, int):
        return False
    rng = key_range(f)
    assert rng is not None, "every numeric key has a range"
    ok = math.isfinite(value) and rng.lo <= value <= rng.hi
    return ok and CROSS_CHECKS.get(dotted, lambda v: True)(value)


def _mid_value(f: Any) -> Any:
    rng = key_range(f)
    v = math.sqrt(max(rng.lo, 1e-3) * rng.hi) if rng.lo >= 0 else (rng.lo + rng.hi) / 2
    return int(v) if isinstance(f.default, int) else v


def test_config_fuzz_every_key_refused_at_load_with_its_key_named_or_accepted():
    all_keys = keys()
    assert len(all_keys) >= 45  # enumerated from the dataclasses: a new key cannot be missed
    checked = 0
    for dotted, f in all_keys:
        values = list(FUZZ_VALUES)
        if key_range(f) is not None:
            values.append(_mid_value(f))
        if key_choices(f) is not None:
            values.append("not-a-choice")
        for value in values:
            valid = _expected_valid(f, value, dotted)
            if valid is None:
                continue
            if valid:
                cfg = DaemonConfig.from_dict(_nest(dotted, value))
                got = cfg
                for part in dotted.split("."):
                    got = getattr(got, part)
                assert got == value, (dotted, value)
            else:
                e = _err(dotted, value)
                assert e.key == dotted, (dotted, value, str(e))
                rng = key_range(f)
                if rng is not None:
                    assert rng.text() in str(e), (dotted, value, str(e))
                if isinstance(value, float) and not isinstance(f.default, str):
                    assert repr(value) in str(e), (dotted, value, str(e))
            checked += 1
    assert checked > 500


def test_config_fuzz_through_toml_files(tmp_path):
    """The same refusals when the values come from a file (nan/inf are TOML floats)."""
    p = tmp_path / "c.toml"
    for dotted, f in keys():
        section, _, name = dotted.rpartition(".")
        for text in ("nan", "inf", "-1", "1e300"):
            p.write_text((f"[{section}]\n" if section else "") + f"{name} = {text}\n")
            value = tomllib.loads(p.read_text())
            value = value[section][name] if section else value[name]
            if _expected_valid(f, value, dotted):
                DaemonConfig.load(p)
                continue
            with pytest.raises(ConfigError) as ei:
                DaemonConfig.load(p)
            assert ei.value.key == dotted, (dotted, text, str(ei.value))


def test_every_key_has_a_documented_range_in_config_dump():
    out = dump_toml(DaemonConfig())
    assert DaemonConfig.from_dict(tomllib.loads(out)) == DaemonConfig()
    for dotted, f in keys():
        assert f.metadata.get("doc"), f"{dotted} has no documentation"
        comment = key_comment(f)
        first = comment.split()[0]
        assert first in out, dotted
        rng = key_range(f)
        if rng is not None:
            assert rng.text() in " ".join(out.split()), dotted
        if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            assert rng is not None, f"numeric {dotted} has no range"


def test_cli_flags_are_checked_like_the_file(capsys):
    from bubble_rt.cli import main

    assert main(["serve", "--sensor-id", "a b", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "sensor_id" in err and "'a b'" in err
    assert main(["serve", "--mesh", "/nonexistent/mesh.vtk", "--duration", "0.1"]) == 2
    assert "estimator.mesh" in capsys.readouterr().err


# ------------------------------------------------------------------------------ the runs
def test_constant_nan_pressure_is_refused_at_load():
    e = _err("pressure.source", "constant:nan")
    assert e.key == "pressure.source"
    assert "nan" in str(e) and "[30000, 200000]" in str(e)
    e = _err("pressure.source", "constant:1e300")
    assert "1e+300" in str(e)
    DaemonConfig.from_dict(_nest("pressure.source", "constant:101325"))


def test_mesh_that_is_not_a_mesh_stops_the_start(tmp_path):
    bad = tmp_path / "hostname"
    bad.write_text("myhost\n")
    pub, ctl = ANY_PORT, ANY_PORT
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "serve", "--mesh", str(bad)]
        + ["--pub", pub, "--control", ctl, "--duration", "5"],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert "estimator.mesh" in proc.stderr and str(bad) in proc.stderr
    assert "Traceback" not in proc.stderr


def test_huge_thickness_is_refused_at_load():
    e = _err("estimator.thickness", 1e300)
    assert e.key == "estimator.thickness" and "[1e-05, 0.01] m" in str(e) and "1e+300" in str(e)


def test_opencv_threads_are_bounded():
    e = _err("processing.opencv_threads", 100000000000)
    assert e.key == "processing.opencv_threads" and "[0, 256]" in str(e)
    assert "100000000000" in str(e)


def test_huge_shutdown_timeout_is_refused_and_the_largest_stops_in_time():
    e = _err("shutdown_timeout_s", 1e300)
    assert e.key == "shutdown_timeout_s" and "[0.1, 600] s" in str(e)
    cfg = fake_config(shutdown_timeout_s=600.0)
    d = Daemon(
        cfg, camera=ScriptedCamera(), pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    assert d.wait_ready(20)
    # No OverflowError, and stop returns with every thread ended (waiting out the 600 s
    # timeout would hit this test's own timeout).
    d.stop()
    assert d.alive_threads() == []


def test_huge_reference_frame_count_is_refused_and_sigint_before_ready_exits_cleanly(tmp_path):
    e = _err("reference.frames", 1000000000)
    assert e.key == "reference.frames" and "[1, 300]" in str(e)
    # The largest accepted count on the real simulated scene: never ready within the test,
    # then SIGINT: a clean exit, no std::terminate, no traceback.
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[reference]\nframes = 300\n[network]\npub = "{ANY_PORT}"\ncontrol = "{ANY_PORT}"\n'
        "[estimator]\nmesh = 'coarse'\n"
    )
    served = ServedProcess(
        [sys.executable, "-m", "bubble_rt", "serve", "--config", str(cfg)], env=_env()
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


def test_recording_path_under_an_existing_file_is_a_clear_error(tmp_path):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    pub, ctl = ANY_PORT, ANY_PORT
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "serve", "--record", str(a_file / "run.mcap")]
        + ["--pub", pub, "--control", ctl, "--duration", "5"],
        env=_env(),
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


class FailingProcessor(FakeProcessor):
    """Every frame fails in stage one (a source that keeps producing unusable frames)."""

    def stage1(self, frame):  # type: ignore[no-untyped-def]
        raise ValueError("frame unusable: no valid depth")


def test_source_that_keeps_failing_is_degraded_with_reason_and_counted_no_log_per_frame(caplog):
    caplog.set_level(logging.WARNING, logger="bubble_rt.daemon")
    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(rate_hz=100.0),
        pressure=constant_pressure(),
        processor_factory=FailingProcessor,
    ).start()
    try:
        assert d.wait_ready(20)

        def counted_50_failures() -> bool:
            return status_of(d).sources["daemon"]["error_counts"].get("deformation", 0) >= 50

        assert wait_for(counted_50_failures, 20)
        with Controller(d.control_address) as c:
            st = c.status()
        assert st.state == "degraded", st.reason
        assert "cannot produce frames" in st.reason and "no valid depth" in st.reason
        assert st.sources["daemon"]["error_counts"]["deformation"] >= 50
        assert d.frames_published == 0
    finally:
        d.stop()
    lines = [r for r in caplog.records if "deformation" in r.getMessage()]
    assert 1 <= len(lines) <= 2, [r.getMessage() for r in lines]  # not one per frame
    assert not any(r.exc_info for r in caplog.records)


# ------------------------------------------------------------------------------ replay
def _forces(msgs: Any) -> dict[int, np.ndarray]:
    return {int(m.frame_index): np.asarray(list(m.net_force)) for m in msgs}


def test_replay_of_a_recording_started_mid_run_in_contact_reproduces_the_live_forces(tmp_path):
    from bubble_rt.io.mcap import TOPIC_SETTINGS, McapRecording, iter_messages

    path, out = tmp_path / "mid.mcap", tmp_path / "replayed.mcap"
    cfg = DaemonConfig().with_overrides(
        **{
            "network.pub": ANY_PORT,
            "network.control": ANY_PORT,
            "estimator.mesh": "coarse",
            "solver.time_limit_ms": 0.0,  # a time-limited solve depends on the machine's load
        }
    )
    d = Daemon(cfg).start()
    try:
        assert d.wait_ready(180)
        with Subscriber(d.pub_address, d.control_address, timeout_s=30) as sub:
            touching = next(
                (f for f in sub.frames(timeout_s=60) if np.linalg.norm(f.net_force) > 0.3), None
            )
            assert touching is not None, "the demo scene never touched"
        with Controller(d.control_address) as c:
            n = d.frames_published
            c.set_params(k_f=0.5)  # a live change the replay must know about
            # Applied: a frame finished after the request took the pending change.
            assert wait_for(lambda: d.frames_published >= n + 2, 30)
            c.record_start(str(path))
            n = d.frames_published
            assert wait_for(lambda: d.frames_published >= n + 30, 60)
            c.record_stop()
    finally:
        d.stop()
    rec = McapRecording(path)
    live = _forces(rec.force_frames())
    assert len(live) >= 20
    first = min(live)
    assert np.linalg.norm(live[first]) > 0.1  # recording started during contact
    settings = [m for t, m, _, _ in iter_messages(path) if t == TOPIC_SETTINGS]
    assert settings and "k_f = 0.5" in settings[0].config_toml
    assert rec.has_reference and rec.mesh is not None

    cfg2 = cfg.with_overrides(
        **{
            "network.pub": ANY_PORT,
            "network.control": ANY_PORT,
            "camera.source": f"replay:{path}",
            "camera.pace": "fast",
            "camera.loop": False,
            "recording.path": str(out),
            "recording.queue": 100000,
        }
    )
    assert cfg2.estimator.k_f != 0.5  # the replay's own config differs from the live one
    # The replay's outputs as it recorded them itself (no subscriber joining late).
    d2 = Daemon(cfg2).start()
    try:
        assert wait_for(lambda: d2.frames_published >= len(live), 120)
    finally:
        d2.stop()
    replayed = _forces(McapRecording(out).force_frames())
    assert set(replayed) == set(live)
    diff = np.array([np.linalg.norm(replayed[k] - live[k]) for k in sorted(live)])
    assert diff.max() < 1e-9, diff.max()


# ------------------------------------------------------------------------------ record command
def test_record_command_says_the_daemon_is_gone(tmp_path):
    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    out = tmp_path / "r.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bubble_rt", "record", "-o", str(out)]
        + ["--control", d.control_address],
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert d.wait_ready(20)
        assert wait_for(lambda: d.recorder is not None, 30)
        recorder = d.recorder
        assert wait_for(lambda: recorder.written >= 10, 30)  # the command's recording runs
    finally:
        d.stop()  # the daemon goes away while `bubble-rt record` runs
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    assert "is gone" in err and "Traceback" not in err
    assert "was finalised" in err  # the daemon's stop finalised it


def test_record_command_without_a_daemon_says_so(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "record", "-o", str(tmp_path / "r.mcap")]
        + ["--control", nobody_listens(tmp_path)],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1
    assert "no daemon answers" in proc.stderr
