"""Simulation truth beside each published frame (issue 12 item 6): ForceFrame.sim_truth is set
for frames from the simulator, absent for anything else, and `echo` shows it beside the
estimate."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.commands.echo import echo, format_line
from bubble_rt.daemon.service import Daemon
from bubble_rt.io import protocol
from bubble_rt.io.client import Subscriber
from daemon_fakes import FakeProcessor, fake_config
from sim_recordings import TINY_SCENE

pytestmark = pytest.mark.timeout(300)


def _frame_msg(n: int = 6, truth: bool = True):  # type: ignore[no-untyped-def]
    contact = np.zeros(n, bool)
    contact[[1, 2]] = True
    msg = protocol.encode_force_frame(
        sensor_id="s",
        seq=7,
        frame_index=3,
        capture_time_ns=1_000_000,
        mesh_id="m",
        net_force=[0.1, -0.2, -0.9],
        node_forces=np.zeros((n, 3)),
        normal_pressure=np.zeros(n),
        contact=contact,
    )
    if truth:
        true_contact = np.zeros(n, bool)
        true_contact[[2, 3]] = True
        protocol.set_sim_truth(msg, np.array([0.05, -0.1, -1.25]), true_contact)
    protocol.stamp_publish(msg, 3_000_000)
    return msg


def test_sim_truth_encode_decode_round_trip():
    f = protocol.decode_force_frame(_frame_msg().SerializeToString())
    assert f.has_truth
    np.testing.assert_allclose(f.true_net_force, [0.05, -0.1, -1.25])
    assert f.true_contact is not None
    assert f.true_contact.tolist() == [False, False, True, True, False, False]
    s = f.summary()["sim_truth"]
    assert s["contact_nodes"] == 2 and s["contact_iou"] == pytest.approx(1 / 3, abs=1e-4)
    assert s["force_n"] == pytest.approx(np.linalg.norm([0.05, -0.1, -1.25]), abs=1e-5)


def test_force_frame_without_truth_decodes_as_absent():
    msg = _frame_msg(truth=False)
    assert not msg.HasField("sim_truth")
    f = protocol.decode_force_frame(msg.SerializeToString())
    assert not f.has_truth and f.true_net_force is None and f.true_contact is None
    assert "sim_truth" not in f.summary()


def test_sim_truth_with_wrong_force_size_is_a_protocol_error():
    msg = _frame_msg()
    msg.sim_truth.net_force.append(1.0)
    with pytest.raises(protocol.ProtocolError, match="sim_truth.net_force"):
        protocol.decode_force_frame(msg.SerializeToString())


def test_echo_formats_estimate_and_truth_side_by_side():
    line = format_line(protocol.decode_force_frame(_frame_msg()), 30.0, "running")
    est, _, truth = line.partition("| true F")
    assert "F [ +0.100  -0.200  -0.900] N" in est and "contact   2 nodes" in est
    assert "[ +0.050  -0.100  -1.250] N" in truth and "|F|  1.255 N" in truth
    assert "contact   2 nodes IoU 0.33" in truth and truth.rstrip().endswith("running")
    plain = format_line(protocol.decode_force_frame(_frame_msg(truth=False)), 30.0, "running")
    assert "true" not in plain


def _collect(daemon: Daemon, count: int) -> list[protocol.ForceFrameData]:
    with Subscriber(daemon.pub_address, daemon.control_address, timeout_s=120) as sub:
        return list(sub.frames(count=count, timeout_s=120))


def test_daemon_on_simulated_scene_publishes_truth(tmp_path, monkeypatch):
    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    cfg = fake_config(
        **{
            "camera.source": f"sim:{scene}",
            "camera.pace": "fast",
            "camera.loop": True,
            "camera.stall_timeout_s": 30.0,
            "reference.frames": 2,
        }
    )
    d = Daemon(cfg, processor_factory=FakeProcessor).start()
    try:
        frames = _collect(d, 6)
        # What `serve --echo` runs: estimate and truth side by side on every line.
        printed = io.StringIO()
        assert echo(d.pub_address, d.control_address, count=3, timeout_s=60, out=printed) == 0
    finally:
        d.stop()
    lines = printed.getvalue().splitlines()
    assert len(lines) == 3 and all("| true F [" in ln for ln in lines)
    assert len(frames) == 6
    n = frames[0].node_forces.shape[0]
    for f in frames:
        assert f.has_truth and f.true_contact is not None and f.true_contact.shape == (n,)
    true_f = np.array([f.true_net_force for f in frames])
    # The tiny scene presses into the dome: true forces point down (-z) and reach ~1.5 N.
    assert true_f[:, 2].min() < -0.5 and np.all(true_f[:, 2] <= 1e-6)
    assert any(f.true_contact.any() for f in frames if f.true_contact is not None)
    assert "sim_truth" in json.loads(json.dumps(frames[-1].summary()))


def test_replay_of_real_layout_recording_publishes_no_truth(tmp_path, monkeypatch):
    from bubble_rt.sim.simulator import Simulator
    from sim_recordings import with_wrench, write_punyo

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    sim = Simulator(str(scene))
    frames = list(sim.reference_frames(2)) + list(sim.frames())
    rec = write_punyo(
        Path(tmp_path / "punyo"), with_wrench(frames, np.eye(3), np.zeros(6)), sim.camera
    )
    cfg = fake_config(
        **{
            "camera.source": f"replay:{rec}",
            "camera.pace": "fast",
            "camera.loop": False,
            "camera.stall_timeout_s": 30.0,
            "reference.frames": 2,
        }
    )
    d = Daemon(cfg, processor_factory=FakeProcessor).start()
    try:
        got = _collect(d, 6)
    finally:
        d.stop()
    assert len(got) == 6
    assert not any(f.has_truth for f in got)
