"""MCAP recordings: round trip, crash safety, replay through the daemon to the same outputs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.daemon.service import Daemon
from bubble_rt.daemon.sources import ReplayCamera
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


def test_images_use_foxglove_image_schemas(tmp_path):
    p = tmp_path / "r.mcap"
    write_recording(p, [make_frame(0)], Camera.d405())
    msgs = {t: m for t, m, _, _ in iter_messages(p)}
    assert type(msgs[TOPIC_RGB]).DESCRIPTOR.full_name == "foxglove.CompressedImage"
    assert msgs[TOPIC_RGB].format == "png"  # write_recording keeps colour lossless
    assert type(msgs[TOPIC_DEPTH]).DESCRIPTOR.full_name == "foxglove.RawImage"
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
    p = tmp_path / "crash.mcap"
    script = textwrap.dedent(
        f"""
        import sys, time
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from daemon_fakes import make_frame
        from bubble_rt.camera import Camera
        from bubble_rt.io.mcap import Recorder
        rec = Recorder({str(p)!r}, Camera.d405(), chunk_size=1 << 30, flush_s=0.05)
        for i in range(10):
            rec.write_frame(make_frame(i))
        time.sleep(0.5)  # the writer flushes its chunk
        print("flushed", flush=True)
        for i in range(10, 20):
            rec.write_frame(make_frame(i))
        time.sleep(60)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=dict(os.environ)
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "flushed"
        time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
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
        end = time.monotonic() + 20
        while d.frames_published < 30 and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        d.stop()
    rec = McapRecording(p)
    recorded = {m.frame_index: np.asarray(m.net_force) for m in rec.force_frames()}
    assert len(recorded) >= 20 and rec.has_reference
    torques = {m.frame_index: np.asarray(m.net_torque) for m in rec.force_frames()}
    assert all(t.shape == (3,) and np.abs(t).max() > 0 for t in torques.values())

    p2 = tmp_path / "replayed.mcap"
    d3 = Daemon(
        fake_config(**{"camera.pace": "fast", "recording.path": str(p2)}),
        camera=ReplayCamera(str(p), realtime=False, loop=False),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    try:
        end = time.monotonic() + 30
        while d3.frames_published < len(rec) and time.monotonic() < end:
            time.sleep(0.05)
        assert d3.frames_dropped == 0  # fast replay is lossless
    finally:
        d3.stop()
    assert d3.frames_published == len(rec)
    replayed = {m.frame_index: np.asarray(m.net_force) for m in McapRecording(p2).force_frames()}
    replayed_tau = {
        m.frame_index: np.asarray(m.net_torque) for m in McapRecording(p2).force_frames()
    }
    common = set(recorded) & set(replayed)
    assert len(common) >= 20
    for k in common:
        np.testing.assert_allclose(replayed[k], recorded[k])
        np.testing.assert_allclose(replayed_tau[k], torques[k])


def _forces_by_frame(path: Path) -> dict[int, np.ndarray]:
    return {
        int(m.frame_index): np.asarray(m.node_forces) for m in McapRecording(path).force_frames()
    }


def test_lossless_recording_replays_to_identical_estimator_forces(tmp_path):
    """Issue 21: the demo scene through the real estimator, recorded with lossless colour
    (png) and the zstd-compressed float depth, replays to the live run's node forces, every
    frame, to the last bit."""
    live, again = tmp_path / "live.mcap", tmp_path / "replay.mcap"
    common = {
        "camera.pace": "fast",
        "camera.loop": False,
        "estimator.mesh": "coarse",
        "recording.color": "png",
        "recording.queue": 100_000,  # the test compares every frame: the writer drops none
        # A solve cut by its time budget depends on the machine's load, not on the input.
        "solver.time_limit_ms": 0.0,
    }
    d = Daemon(fake_config(**common, **{"camera.source": "sim", "recording.path": str(live)}))
    d.start()
    try:
        assert d.wait_ready(60)
        end = time.monotonic() + 60
        while d.frames_published < 12 and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        writer = d.recorder
        d.stop()
    assert writer.finished.wait(60) and not writer.failed and writer.dropped == 0
    recorded = _forces_by_frame(live)
    assert len(recorded) >= 12
    d2 = Daemon(
        fake_config(**common, **{"camera.source": f"replay:{live}", "recording.path": str(again)})
    )
    d2.start()
    try:
        end = time.monotonic() + 60
        while d2.frames_published < len(recorded) and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        writer = d2.recorder
        d2.stop()
    assert writer.finished.wait(60) and not writer.failed
    replayed = _forces_by_frame(again)
    assert set(recorded) <= set(replayed)
    for k in sorted(recorded):
        assert np.abs(recorded[k]).max() > 0 or k < 3  # forces, not zeros throughout
        np.testing.assert_allclose(replayed[k], recorded[k], rtol=0, atol=1e-12)
    assert max(np.abs(f).max() for f in recorded.values()) > 1e-3
