"""bubble_rt.daemon.control: control requests (set_params, tare, get_mesh, record_start/stop)
and bad requests (random bytes, empty, oversized, wrong version, multipart, raw TCP garbage)
answered with an error reply that names the problem."""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest
import zmq
from bubble_rt.daemon.control import validate_params
from bubble_rt.daemon.service import Daemon
from bubble_rt.io import protocol
from bubble_rt.io.client import ControlError, Controller
from bubble_rt.io.mcap import McapRecording, RecordingPathError
from bubble_rt.io.mcap_writer import Recorder
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    sim_like_camera,
    start,
    start_daemon,
)
from waiting import wait_for

pytestmark = pytest.mark.timeout(60)


def test_set_params_applied_between_frames(daemon):
    d, _ = daemon
    with Controller(d.control_address) as c:
        out = c.set_params(k_f=0.5, youngs_modulus=1.0e6)
        assert out["k_f"] == 0.5 and out["youngs_modulus"] == 1.0e6
        assert "k_f = 0.5" in c.get_config()
    proc = FakeProcessor.instances[-1]
    assert wait_for(lambda: proc.params.get("k_f") == 0.5)
    assert proc.params["youngs_modulus"] == 1.0e6


def test_set_params_refuses_a_parameter_the_running_estimator_lacks():
    # Issue 11: k_f on the frictionless estimator used to answer OK, then raise in the
    # processing stage (frame dropped, change lost). It is refused, by name, and nothing changes.
    d, _ = start(fake_config(**{"estimator.kind": "frictionless"}))
    try:
        proc = FakeProcessor.instances[-1]
        with Controller(d.control_address) as c:
            before = c.get_config()
            with pytest.raises(ControlError, match="no parameter k_f"):
                c.set_params(k_f=0.5, k_const=1500.0)
            assert c.get_config() == before
            out = c.set_params(k_const=1500.0)
            assert out["k_const"] == 1500.0
        assert wait_for(lambda: proc.params.get("k_const") == 1500.0)
        assert "k_f" not in proc.params
        assert d.errors.get("estimator", 0) == 0
    finally:
        d.stop()


def test_set_params_rejects_bad_values(daemon):
    d, _ = daemon
    with Controller(d.control_address) as c:
        with pytest.raises(ControlError, match=r"k_u must be in \[100, 1e\+10\] 1/m\^2, got -3.0"):
            c.set_params(k_u=-3.0)
        with pytest.raises(ControlError, match=r"k_f must be in \[0.0001, 1000\] 1/N, got nan"):
            c.set_params(k_f=float("nan"))
        with pytest.raises(ControlError, match="no parameter given"):
            c.set_params()


def test_tare_recaptures_reference(daemon):
    d, _ = daemon
    proc = FakeProcessor.instances[-1]
    with Controller(d.control_address) as c:
        c.tare()
    assert wait_for(lambda: proc.references == 2)


def test_random_bytes_get_error_replies(daemon):
    d, _ = daemon
    rng = np.random.default_rng(0)
    with Controller(d.control_address) as c:
        for n in (1, 7, 100, 5000):
            rep = c.send_raw(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
            assert not rep.ok and rep.error
        assert c.status().state in ("starting", "running", "degraded")


def test_empty_request_names_the_problem(daemon):
    d, _ = daemon
    with Controller(d.control_address) as c:
        rep = c.send_raw(b"")
    assert not rep.ok and "unknown or empty request" in rep.error


def test_oversized_request_is_refused(daemon):
    d, _ = daemon
    with Controller(d.control_address) as c:
        rep = c.send_raw(b"\x00" * (protocol.MAX_REQUEST_BYTES + 1))
        assert not rep.ok and "too large" in rep.error
        assert c.get_mesh().n_nodes == 227


def test_wrong_protocol_version_is_refused(daemon):
    d, _ = daemon
    req = protocol.make_request("get_status")
    req.protocol_version = 99
    with Controller(d.control_address) as c:
        rep = c.send_raw(req.SerializeToString())
    assert not rep.ok and "protocol_version 99" in rep.error


def test_multipart_request_is_refused(daemon):
    d, _ = daemon
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(d.control_address)
    s.send_multipart([b"", b"a", b"b"])
    assert s.poll(3000)
    parts = s.recv_multipart()
    s.close()
    rep = protocol.parse_reply(parts[-1])
    assert not rep.ok and "exactly one message frame" in rep.error


def test_raw_tcp_garbage_does_not_kill_control(daemon):
    d, _ = daemon
    host, port = d.control_address[6:].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=2) as s:
        s.sendall(os.urandom(4096))
    with Controller(d.control_address) as c:
        assert c.get_mesh().n_nodes == 227


def test_get_mesh_before_reference_is_an_error():
    cam = ScriptedCamera()
    cam.pause.set()
    d = Daemon(
        fake_config(), camera=cam, pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    try:
        with Controller(d.control_address) as c:
            with pytest.raises(ControlError, match="mesh not ready"):
                c.get_mesh()
            assert c.status().state == "starting"
            with pytest.raises(ControlError, match="reference is still being captured"):
                c.tare()
    finally:
        d.stop()


def test_record_start_stop_via_control(daemon, tmp_path):
    from bubble_rt.io.mcap import McapRecording

    d, _ = daemon
    path = tmp_path / "rec.mcap"
    with Controller(d.control_address) as c:
        assert c.record_start(str(path)) == str(path.resolve())
        with pytest.raises(ControlError, match="already recording"):
            c.record_start(str(path))
        n = d.frames_published
        assert wait_for(lambda: d.frames_published > n + 10)
        assert c.record_stop() == str(path.resolve())
        with pytest.raises(ControlError, match="not recording"):
            c.record_stop()
    rec = McapRecording(path)
    assert len(rec) >= 5 and rec.has_reference and rec.mesh is not None
    assert len(list(rec.force_frames())) >= 5


def test_validate_params_names_the_parameter():
    assert validate_params({"k_const": -1.0}) == (
        "set_params: k_const must be in [0, 1e+06] Pa, got -1.0"
    )
    assert validate_params({"k_linear": 0.0}) is None


@pytest.mark.timeout(120)
def test_record_start_over_control_writes_a_readable_file(tmp_path):
    """record_start used to leave a 178-byte file while the status said "recording"."""
    d = start_daemon(sim_like_camera())
    out = tmp_path / "ctl.mcap"
    try:
        with Controller(d.control_address) as c:
            assert c.record_start(str(out)) == str(out.resolve())
            # Waits on force frames published since the start, not on messages written: the
            # camera's messages outnumber the force frames by a ratio set by the machine.
            start = d.frames_published
            assert wait_for(lambda: d.recorder is not None and d.recorder.written > 30)
            assert wait_for(lambda: d.frames_published >= start + 8)
            st = c.status()
            assert st.recording and st.recording_error == ""
            assert c.record_stop() == str(out.resolve())
    finally:
        d.stop()
    rec = McapRecording(out)
    assert rec.report.complete and len(rec) >= 5 and rec.has_reference


@pytest.mark.timeout(120)
def test_record_start_refuses_an_existing_file_unless_asked_to_overwrite(tmp_path):
    """A text file given to record_start became a 60 MB MCAP."""
    text = tmp_path / "notes.txt"
    text.write_text("keep me\n")
    d = start_daemon()
    try:
        with Controller(d.control_address) as c:
            with pytest.raises(ControlError, match="file exists"):
                c.record_start(str(text))
            assert text.read_text() == "keep me\n" and d.recorder is None
            c.record_start(str(text), overwrite=True)
            assert wait_for(lambda: d.recorder is not None and d.recorder.written > 0)
            c.record_stop()
        assert text.read_bytes().startswith(b"\x89MCAP0\r\n")
    finally:
        d.stop()


@pytest.mark.timeout(120)
def test_record_start_creates_no_folders(tmp_path):
    d = start_daemon()
    try:
        with Controller(d.control_address) as c:
            with pytest.raises(ControlError, match="does not exist"):
                c.record_start(str(tmp_path / "a" / "b" / "x.mcap"))
        assert not (tmp_path / "a").exists()
    finally:
        d.stop()


@pytest.mark.timeout(120)
def test_record_start_refuses_a_fifo_without_blocking_the_control_thread(tmp_path):
    """A FIFO path blocked the control thread until something read it."""
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    d = start_daemon()
    try:
        # A control thread blocked on the FIFO would leave these requests unanswered: the
        # Controller's timeout would raise TimeoutError, not the refusal.
        with Controller(d.control_address, timeout_s=2.0) as c:
            with pytest.raises(ControlError, match="not a regular file .*FIFO"):
                c.record_start(str(fifo), overwrite=True)
            with pytest.raises(ControlError, match="FIFO"):
                c.record_start(str(fifo))
            assert wait_for(lambda: c.status().state == "running")
    finally:
        d.stop()
    with pytest.raises(RecordingPathError, match="FIFO"):
        Recorder(fifo, overwrite=True)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "param,value", [("k_u", 5e-324), ("youngs_modulus", 1e308), ("k_f", 1e308)]
)
def test_set_params_out_of_range_is_refused_and_not_applied(param, value):
    """These answered OK, then every frame failed (singular matrix) or was all zeros."""
    d = start_daemon()
    try:
        with Controller(d.control_address) as c:
            n = d.frames_published
            with pytest.raises(ControlError, match=f"set_params: {param} must be in"):
                c.set_params(**{param: value})
            # Two frames finished since: a change queued by the request would be applied.
            assert wait_for(lambda: d.frames_published >= n + 2)
            assert param not in d.processor.params
            assert f"{param} = {value!r}" not in c.get_config()
            assert c.status().state == "running"
    finally:
        d.stop()


@pytest.mark.timeout(120)
def test_oversize_request_gets_a_reply_the_client_can_read():
    """17 MB requests made ZeroMQ drop the connection silently."""
    d = start_daemon()
    try:
        assert d.ctl.getsockopt(zmq.MAXMSGSIZE) == protocol.MAX_MESSAGE_BYTES
        with Controller(d.control_address, timeout_s=5.0) as c:
            rep = c.send_raw(b"\x00" * (17 * 1024 * 1024))
            assert not rep.ok and "request too large: 17825792 bytes" in rep.error
            assert "ZMQ_MAXMSGSIZE" in rep.error
            rep = c.send_raw(b"\x00" * (10 * 1024 * 1024))  # answered by the daemon
            assert not rep.ok and rep.error.startswith("request too large: 10485760 bytes")
            # The daemon survived both: it goes on to run (it may still be capturing its
            # reference when the requests are answered).
            assert wait_for(lambda: c.status().state == "running")
    finally:
        d.stop()
