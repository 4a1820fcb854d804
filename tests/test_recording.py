"""MCAP recordings: round trip, crash safety, replay through the daemon to the same outputs."""

from __future__ import annotations

import os
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.config import DaemonConfig
from bubble_rt.daemon.service import Daemon
from bubble_rt.daemon.sources import ReplayCamera, SourceError
from bubble_rt.io.client import ControlError, Controller, Subscriber
from bubble_rt.io.mcap import (
    TOPIC_DEPTH,
    TOPIC_RGB,
    McapRecording,
    RecordingWarning,
    iter_messages,
)
from bubble_rt.io.mcap_scan import McapFileError, ReadReport
from bubble_rt.io.mcap_writer import Recorder, write_recording
from bubble_rt.sensor import profile_for_layout
from daemon_fakes import (
    CAM,
    FakeProcessor,
    H,
    ScriptedCamera,
    W,
    constant_pressure,
    fake_config,
    make_frame,
)
from recording_fakes import killed_recording, log_times
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


def test_a_recording_names_the_sensor_profile_it_was_recorded_with(tmp_path):
    # `estimate` and `eval --recording` resolve profile = "auto" by the recording's layout: a
    # recorded Punyo (the daemon wrote [estimator] profile = "punyo") is a Punyo offline too,
    # not the default's (with the sim profile a simulated Punyo's reference read 2.9 N).
    cam = Camera.d405(width=32, height=24, cx=16, cy=12)
    p = tmp_path / "r.mcap"
    write_recording(p, [make_frame(i) for i in range(2)], cam)
    rec = McapRecording(p)
    assert rec.layout == "mcap"  # no settings recorded
    for toml, layout in (
        ('[estimator]\nprofile = "punyo"\nambient_pa = 86300.0\n', "punyo"),
        ('[estimator]\nprofile = "sim"\n', "sim"),
        ('[estimator]\nprofile = "auto"\n', "mcap"),
        ('[estimator]\nprofile = "gel"\n', "mcap"),
        ("[estimator]\nprofile = [1]\n", "mcap"),
        ("estimator = 3\n", "mcap"),
        ("[estimator\nprofile = 'punyo'", "mcap"),  # does not parse
    ):
        rec.settings_toml = toml
        assert rec.layout == layout, toml
        assert profile_for_layout(rec.layout).name == ("punyo" if layout == "punyo" else "sim")


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
        assert wait_for(lambda: d3.frames_published >= len(rec), 30)
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
            # Lossless colour (the default JPEG moves the forces), every frame in the file.
            "recording.color": "png",
            "recording.queue": 100_000,
        }
    )
    d = Daemon(cfg).start()
    try:
        assert d.wait_ready(180)
        with (
            Subscriber(d.pub_address, d.control_address, timeout_s=30) as sub,
            Controller(d.control_address) as c,
        ):
            c.set_params(k_f=0.5)  # a live change the replay must know about
            # Frames from seq n + 1 on began their solve after the change was queued, so they
            # applied it; one of them pressing: the recording starts during contact.
            n = d.frames_published
            touching = next(
                (
                    f
                    for f in sub.frames(timeout_s=60)
                    if f.seq >= n + 1 and np.linalg.norm(f.net_force) > 0.3
                ),
                None,
            )
            assert touching is not None, "the demo scene never touched"
            c.record_start(str(path))
            writer = d.recorder
            n = d.frames_published
            assert wait_for(lambda: d.frames_published >= n + 30, 60)
            try:
                c.record_stop()
            except ControlError as exc:  # PNG encoding lags on a loaded machine
                assert "finalised in the background" in str(exc)
    finally:
        d.stop()
    assert writer.finished.wait(120) and writer.dropped == 0
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
        writer2 = d2.recorder
    finally:
        d2.stop()
    # stop() can leave the file to be finalised in the background on a loaded machine
    assert writer2.finished.wait(120) and writer2.dropped == 0
    replayed = _forces(McapRecording(out).force_frames())
    assert set(replayed) == set(live)
    diff = np.array([np.linalg.norm(replayed[k] - live[k]) for k in sorted(live)])
    assert diff.max() < 1e-9, diff.max()


@pytest.mark.timeout(120)
def test_negative_source_times_never_reach_the_file(tmp_path):
    """serve --record on the sim scene died with struct.error: negative MCAP log times."""
    p = tmp_path / "neg.mcap"
    frames = [replace(make_frame(i), t=-0.1 + i / 30.0) for i in range(6)]
    ref = [replace(make_frame(50 + k), t=-0.2 + k / 30.0, index=k - 2) for k in range(2)]
    assert write_recording(p, frames, CAM, reference=ref) == 6
    from mcap.reader import make_reader

    with open(p, "rb") as f:  # the mcap package's indexed reader: a finalised file
        assert sum(1 for _ in make_reader(f).iter_messages()) > 0
    assert min(log_times(p)) >= 0
    rec = McapRecording(p)
    assert len(rec) == 6 and rec.has_reference and rec.report.complete


@pytest.mark.timeout(120)
def test_killed_recording_is_read_with_a_not_closed_warning(tmp_path):
    """SIGKILL leaves no summary or footer: every reader here reads it and warns."""
    p = tmp_path / "crash.mcap"
    killed_recording(p, frames=12)
    from mcap.reader import make_reader

    with open(p, "rb") as f, pytest.raises(Exception):  # noqa: B017 - the package's reader
        list(make_reader(f).iter_messages())
    with pytest.warns(RecordingWarning, match="not closed"):
        rec = McapRecording(p)
    assert len(rec) >= 10 and not rec.report.closed
    np.testing.assert_array_equal(list(rec)[9].rgb, make_frame(9).rgb)
    report = ReadReport(str(p))
    assert sum(1 for _ in iter_messages(p, report)) >= 30 and not report.closed
    src = ReplayCamera(str(p), realtime=False)  # replay: the warning is in the source status
    assert src.stats.errors.get("recording") == 1 and "not closed" in src.stats.last_error


@pytest.mark.timeout(120)
def test_recorder_write_failure_is_reported_at_once(tmp_path):
    """Recording to /dev/full killed the writer thread with a traceback."""
    seen: list[BaseException] = []
    old = threading.excepthook
    threading.excepthook = lambda a: seen.append(a.exc_value)  # type: ignore[assignment]
    try:
        rec = Recorder("/dev/full", CAM, file=open("/dev/full", "wb"))  # noqa: SIM115
        assert wait_for(lambda: rec.failed != "", 2.0)
        assert "No space left on device" in rec.failed
        for i in range(5):
            rec.write_frame(make_frame(i))  # never raises, counted as dropped
        assert rec.dropped >= 5
        assert rec.close() is False
    finally:
        threading.excepthook = old
    assert seen == []


def closed_mcap(p: Path, n: int = 40) -> None:
    rec = Recorder(p, CAM, chunk_size=4000, compression="lz4", queue_size=10000)
    for i in range(n):
        rec.write_frame(
            replace(
                make_frame(i),
                rgb=np.random.default_rng(i).integers(0, 255, (H, W, 3), dtype=np.uint8),
            )
        )
    rec.close()


@pytest.mark.timeout(120)
def test_truncated_mcap_reports_what_was_lost(tmp_path):
    """Half a file replayed 13 of 40 frames with no warning."""
    p = tmp_path / "full.mcap"
    closed_mcap(p)
    cut = tmp_path / "half.mcap"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.warns(RecordingWarning, match="not closed") as w:
        rec = McapRecording(cut)
    assert 5 < len(rec) < 40
    assert "bytes unreadable" in str(w[0].message) or "not closed" in str(w[0].message)
    src = ReplayCamera(str(cut), realtime=False)
    assert src.stats.errors == {"recording": 1} and "not closed" in src.stats.last_error


@pytest.mark.timeout(120)
def test_corrupted_mcap_chunks_are_skipped_and_counted(tmp_path):
    """Two 64-byte corruptions lost 31 of 40 frames silently."""
    p = tmp_path / "full.mcap"
    closed_mcap(p)
    from mcap.reader import make_reader

    with open(p, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes  # type: ignore[union-attr]
    data = bytearray(p.read_bytes())
    for k in (len(chunks) // 4, len(chunks) // 2):  # 64 bytes inside two chunks' data
        at = chunks[k].chunk_start_offset + chunks[k].chunk_length // 2
        data[at : at + 64] = bytes(range(64))
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(RecordingWarning, match="indexed") as w:
        rec = McapRecording(bad)
    r = rec.report
    assert r.closed and r.chunks_skipped == 2 and "damaged chunk" in r.problems[0]
    assert rec.frames_indexed == 40 and 30 <= len(rec) < 40
    assert f"{len(rec)} of 40 frames readable" in str(w[0].message)
    assert [f.index for f in rec] == sorted(f.index for f in rec)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "content", [b"", "prefix", os.urandom(4096)], ids=["empty", "100_bytes", "random"]
)
def test_non_mcap_or_empty_file_is_refused_at_once(tmp_path, content):
    """An empty, 100-byte or random .mcap left the daemon "starting" forever."""
    p = tmp_path / "x.mcap"
    if content == "prefix":
        full = tmp_path / "full.mcap"
        closed_mcap(full, 3)
        content = full.read_bytes()[:100]
    p.write_bytes(content)
    # Refused at construction and at start (a daemon "starting" forever would not raise).
    with pytest.raises(SourceError, match="empty file|not an MCAP file|no frame"):
        ReplayCamera(str(p))
    with pytest.raises(SourceError):
        Daemon(fake_config(**{"camera.source": f"replay:{p}"})).start()
    with pytest.raises(McapFileError):
        McapRecording(p)


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
        assert wait_for(lambda: d.frames_published >= 12, 60)
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
        assert wait_for(lambda: d2.frames_published >= len(recorded), 60)
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
