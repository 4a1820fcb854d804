"""MCAP recordings: round trip, crash safety, replay through the daemon to the same outputs."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.config import DaemonConfig
from bubble_rt.daemon.service import Daemon
from bubble_rt.daemon.sources import ReplayCamera
from bubble_rt.io.client import Controller, Subscriber
from bubble_rt.io.mcap import (
    TOPIC_DEPTH,
    TOPIC_RGB,
    McapRecording,
    Recorder,
    RecordingWarning,
    iter_messages,
    write_recording,
)
from daemon_fakes import FakeProcessor, ScriptedCamera, constant_pressure, fake_config, make_frame
from recording_fakes import killed_recording
from waiting import ANY_PORT, wait_for

pytestmark = pytest.mark.timeout(90)


def test_round_trip_frames_camera_and_reference(tmp_path):
    cam = Camera.d405(width=32, height=24, cx=16, cy=12)
    frames = [make_frame(i) for i in range(5)]
    # Reference frames come before the stream: the simulator gives them negative indices.
    ref = [replace(make_frame(100 + i), index=i - 2) for i in range(2)]
    p = tmp_path / "r.mcap"
    assert write_recording(p, frames, cam, reference=ref) == 5
    rec = McapRecording(p)
    assert len(rec) == 5 and rec.camera == cam
    got = list(rec)
    assert [f.index for f in got] == [0, 1, 2, 3, 4]
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        assert a.pressure_pa == b.pressure_pa and a.t == pytest.approx(b.t)
    r = rec.reference_frames(10)
    assert len(r) == 2 and r[0].rgb[0, 0, 0] == 100 and [f.index for f in r] == [-2, -1]


def test_images_use_foxglove_raw_image_schema(tmp_path):
    p = tmp_path / "r.mcap"
    write_recording(p, [make_frame(0)], Camera.d405())
    msgs = {t: m for t, m, _, _ in iter_messages(p)}
    assert type(msgs[TOPIC_RGB]).DESCRIPTOR.full_name == "foxglove.RawImage"
    assert msgs[TOPIC_RGB].encoding == "rgb8" and msgs[TOPIC_RGB].step == 32 * 3
    assert msgs[TOPIC_DEPTH].encoding == "32FC1" and msgs[TOPIC_DEPTH].step == 32 * 4


def test_truncated_file_reads_up_to_last_chunk(tmp_path):
    p = tmp_path / "r.mcap"
    rec = Recorder(p, Camera.d405(), chunk_size=20_000, compression="none", queue_size=1000)
    for i in range(20):
        rec.write_frame(make_frame(i))
    rec.close()
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.warns(RecordingWarning, match="not closed"):
        got = list(McapRecording(cut))
    assert 3 <= len(got) < 20
    assert [f.index for f in got] == list(range(len(got)))


def test_recording_survives_a_killed_process(tmp_path):
    p = killed_recording(tmp_path / "crash.mcap", frames=10, more=10)
    with pytest.warns(RecordingWarning, match="not closed"):
        got = list(McapRecording(p))
    assert len(got) >= 10
    np.testing.assert_array_equal(got[9].rgb, make_frame(9).rgb)


def test_recording_replays_to_the_same_outputs(tmp_path):
    p = tmp_path / "live.mcap"
    d = Daemon(
        fake_config(**{"recording.path": str(p)}),
        camera=ScriptedCamera(rate_hz=60.0),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    try:
        assert d.wait_ready(20)
        assert wait_for(lambda: d.frames_published >= 30, 20)
    finally:
        d.stop()
    rec = McapRecording(p)
    recorded = {m.frame_index: np.asarray(m.net_force) for m in rec.force_frames()}
    assert len(recorded) >= 20 and rec.has_reference

    p2 = tmp_path / "replayed.mcap"
    d3 = Daemon(
        fake_config(**{"camera.pace": "fast", "recording.path": str(p2)}),
        camera=ReplayCamera(str(p), realtime=False, loop=False),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    try:
        assert wait_for(lambda: d3.frames_published >= len(rec), 30)
        assert d3.frames_dropped == 0  # fast replay is lossless
    finally:
        d3.stop()
    assert d3.frames_published == len(rec)
    replayed = {m.frame_index: np.asarray(m.net_force) for m in McapRecording(p2).force_frames()}
    common = set(recorded) & set(replayed)
    assert len(common) >= 20
    for k in common:
        np.testing.assert_allclose(replayed[k], recorded[k])


# ------------------------------------------------------------------------------ replay
def _forces(msgs: Any) -> dict[int, np.ndarray]:
    return {int(m.frame_index): np.asarray(list(m.net_force)) for m in msgs}


@pytest.mark.timeout(240)
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
