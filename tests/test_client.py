"""Client: Controller timeouts and errors, Subscriber frames, `bubble-rt echo` output."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading

import pytest
from bubble_rt.commands.echo import RateMeter, echo, format_line
from bubble_rt.daemon.service import Daemon
from bubble_rt.io.client import ControlError, Controller, Subscriber, control_address_for
from daemon_fakes import FakeProcessor, ScriptedCamera, constant_pressure, fake_config
from waiting import child_env, nobody_listens, wait_for

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def daemon():
    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    assert d.wait_ready(20)
    yield d
    d.stop()


def test_control_address_for_tcp():
    assert control_address_for("tcp://127.0.0.1:5555") == "tcp://127.0.0.1:5556"
    assert control_address_for("ipc:///tmp/x") is None


def test_controller_times_out_without_daemon(tmp_path):
    with Controller(nobody_listens(tmp_path), timeout_s=0.2) as c:
        with pytest.raises(TimeoutError, match="no reply"):
            c.status()
        with pytest.raises(TimeoutError):  # the socket was reset and is usable again
            c.status()


def test_controller_error_reply_raises(daemon):
    with Controller(daemon.control_address) as c:
        with pytest.raises(ControlError, match="record_stop: not recording"):
            c.record_stop()


def test_subscriber_frames_have_numpy_arrays(daemon):
    with Subscriber(daemon.pub_address, daemon.control_address) as sub:
        f = next(sub.frames(count=1, timeout_s=5))
        assert f.node_forces.dtype.kind == "f" and f.contact.dtype == bool
        assert sub.mesh.n_nodes == f.node_forces.shape[0]


def test_subscriber_filters_by_sensor(daemon):
    with Subscriber(daemon.pub_address, daemon.control_address, sensor_id="other") as sub:
        assert list(sub.frames(count=1, timeout_s=0.5)) == []


def test_subscriber_over_ipc(tmp_path):
    cfg = fake_config(
        **{"network.pub": f"ipc://{tmp_path}/pub", "network.control": f"ipc://{tmp_path}/ctl"}
    )
    d = Daemon(
        cfg, camera=ScriptedCamera(), pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    try:
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert len(list(sub.frames(count=2, timeout_s=10))) == 2
    finally:
        d.stop()


def test_echo_prints_one_line_per_frame(daemon):
    out = io.StringIO()
    assert echo(daemon.pub_address, daemon.control_address, count=3, out=out, timeout_s=10) == 0
    lines = out.getvalue().splitlines()
    assert len(lines) == 3
    assert "Hz" in lines[0] and "lat" in lines[0] and "contact   5 nodes" in lines[0]


def test_echo_json_lines(daemon):
    out = io.StringIO()
    echo(daemon.pub_address, count=2, as_json=True, out=out, timeout_s=10)
    rows = [json.loads(x) for x in out.getvalue().splitlines()]
    assert len(rows) == 2 and rows[0]["contact_nodes"] == 5 and "rate_hz" in rows[0]
    assert rows[0]["net_force"][2] < 0


def test_echo_stops_on_event(daemon):
    stop = threading.Event()
    stop.set()
    assert echo(daemon.pub_address, stop=stop, out=io.StringIO()) == 0


def test_echo_gives_up_without_frames(tmp_path):
    assert echo(nobody_listens(tmp_path), timeout_s=0.3, out=io.StringIO()) == 1


def test_rate_meter():
    r = RateMeter()
    for k in range(31):
        hz = r.add(int(k * 1e9 / 30))
    assert hz == pytest.approx(30.0)


def test_format_line_marks_degraded():
    from bubble_rt.io import protocol

    msg = protocol.encode_force_frame(
        sensor_id="s",
        seq=1,
        frame_index=1,
        capture_time_ns=0,
        mesh_id="m",
        net_force=[0, 0, -2.0],
        node_forces=[[0, 0, -2.0]],
        normal_pressure=[1.0],
        contact=[True],
        degraded_reasons=["pressure stale (400 ms)"],
    )
    line = format_line(protocol.decode_force_frame(msg), 30.0, "degraded")
    assert "|F|  2.000 N" in line and "DEGRADED: pressure stale" in line


def test_record_command_records_for_a_duration(daemon, tmp_path):
    import argparse

    from bubble_rt.commands import record
    from bubble_rt.io.mcap import McapRecording

    out = tmp_path / "cli.mcap"
    args = argparse.Namespace(output=str(out), control=daemon.control_address, duration=0.5)
    assert record.run(args) == 0
    assert len(list(McapRecording(out).force_frames())) > 0


def test_record_command_without_daemon_fails_cleanly(tmp_path):
    import argparse

    from bubble_rt.commands import record

    args = argparse.Namespace(
        output=str(tmp_path / "x.mcap"), control=nobody_listens(tmp_path), duration=0.1
    )
    # Controller timeout is 5 s in the command; an absent daemon is reported, not raised.
    assert record.run(args) == 1


@pytest.mark.timeout(240)
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
        env=child_env(),
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


@pytest.mark.timeout(240)
def test_record_command_without_a_daemon_says_so(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "bubble_rt", "record", "-o", str(tmp_path / "r.mcap")]
        + ["--control", nobody_listens(tmp_path)],
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1
    assert "no daemon answers" in proc.stderr
