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
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    start,
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
