"""Issue 15: recordings that always work, bad recordings that are reported, control changes
that cannot break the stream. One named test per reported run (see the issue's items)."""

from __future__ import annotations

import os
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zmq
from bubble_rt.camera import Camera
from bubble_rt.config import ESTIMATOR_RANGES, ConfigError, DaemonConfig
from bubble_rt.daemon.service import Daemon, DaemonError
from bubble_rt.daemon.sources import (
    IterableCamera,
    PressureBuffer,
    ReplayCamera,
    SourceError,
)
from bubble_rt.frames import Frame, FrameError
from bubble_rt.io import protocol
from bubble_rt.io.client import ControlError, Controller
from bubble_rt.io.mcap import (
    TOPIC_DEPTH,
    TOPIC_PRESSURE,
    TOPIC_RGB,
    McapRecording,
    Recorder,
    RecordingPathError,
    RecordingWarning,
    iter_messages,
    raw_image,
    write_recording,
)
from bubble_rt.io.mcap_scan import McapFileError, ReadReport
from bubble_rt.io.protocol import PARAM_NAMES, pb
from bubble_rt.io.recordings import open_recording
from daemon_fakes import (
    P0,
    FakeProcessor,
    H,
    ScriptedCamera,
    W,
    constant_pressure,
    fake_config,
    make_frame,
)
from daemon_fakes import status_of as status
from recording_fakes import killed_recording, make_punyo
from waiting import ANY_PORT, wait_for

pytestmark = pytest.mark.timeout(120)
CAM = Camera.d405(width=W, height=H, cx=W / 2, cy=H / 2)


def sim_like_camera(pressure_pa: float = P0, rate_hz: float = 100.0) -> IterableCamera:
    """Frames on the scene clock from 0 and reference frames at t = -0.1 .. -0.033 s, like
    the simulator's."""

    def frames():  # type: ignore[no-untyped-def]
        for i in range(100000):
            yield replace(make_frame(i), pressure_pa=pressure_pa)

    def reference(n: int) -> list[Frame]:
        return [
            replace(make_frame(500 + k), t=-0.1 + k / 30.0, index=k - n, pressure_pa=pressure_pa)
            for k in range(n)
        ]

    return IterableCamera(frames, CAM, rate_hz=rate_hz, reference=reference, keep_index=True)


def start_daemon(camera=None, pressure=None, **overrides):  # type: ignore[no-untyped-def]
    d = Daemon(
        fake_config(**overrides),
        camera=camera or ScriptedCamera(),
        pressure=pressure or constant_pressure(),
        processor_factory=FakeProcessor,
    ).start()
    assert d.wait_ready(20)
    return d


def log_times(path):  # type: ignore[no-untyped-def]
    return [t for _, _, t, _ in iter_messages(path)]


# ================================================================== recording
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


def test_sim_reference_frames_are_recorded_on_the_daemon_clock(tmp_path):
    """Recording works from the first frame of a source whose reference has t < 0."""
    p = tmp_path / "sim.mcap"
    t0 = time.time()
    d = start_daemon(sim_like_camera(), **{"recording.path": str(p)})
    try:
        assert wait_for(lambda: d.frames_published >= 10)
        assert d.recorder.clamped == 0 and not d.recorder.failed
    finally:
        d.stop()
    rec = McapRecording(p)
    assert rec.report.complete and rec.has_reference and len(rec) >= 10
    ref = rec.reference_frames(10)
    assert all(abs(f.t - t0) < 60 for f in ref), "reference frames on the daemon clock"
    assert min(log_times(p)) >= int(t0 * 1e9) - int(60e9)
    assert len(list(rec.force_frames())) >= 10


def test_record_start_over_control_writes_a_readable_file(tmp_path):
    """record_start used to leave a 178-byte file while the status said "recording"."""
    d = start_daemon(sim_like_camera())
    out = tmp_path / "ctl.mcap"
    try:
        with Controller(d.control_address) as c:
            assert c.record_start(str(out)) == str(out.resolve())
            assert wait_for(lambda: d.recorder is not None and d.recorder.written > 30)
            st = c.status()
            assert st.recording and st.recording_error == ""
            assert c.record_stop() == str(out.resolve())
    finally:
        d.stop()
    rec = McapRecording(out)
    assert rec.report.complete and len(rec) >= 5 and rec.has_reference


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


def test_recover_command_rewrites_a_killed_recording_as_a_finalised_file(tmp_path, capsys):
    from bubble_rt.cli import main
    from mcap.reader import make_reader

    p = tmp_path / "crash.mcap"
    killed_recording(p, frames=12)
    out = tmp_path / "fixed.mcap"
    assert main(["recover", str(p), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "was not closed" in text and f"to {out}" in text
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        n = sum(1 for _ in reader.iter_messages())
    assert n == summary.statistics.message_count >= 36
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a recovered file reads without any warning
        rec = McapRecording(out)
    assert rec.report.complete and len(rec) >= 12 and rec.frames_indexed == len(rec)
    # The output is never overwritten silently.
    assert main(["recover", str(p), "-o", str(out)]) == 1
    assert "file exists" in capsys.readouterr().err


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


def test_daemon_recording_failure_turns_status_to_error_and_stream_goes_on(monkeypatch, tmp_path):
    import bubble_rt.io.mcap as mcap_mod

    monkeypatch.setattr(
        mcap_mod,
        "open_new_file",
        lambda path, overwrite=False: open("/dev/full", "wb"),  # noqa: SIM115
    )
    d = start_daemon()
    try:
        with Controller(d.control_address) as c:
            c.record_start(str(tmp_path / "full.mcap"))
            assert wait_for(lambda: c.status().recording_error != "", 3.0)
            st = c.status()
            assert st.state == "degraded" and "recording failed" in st.reason
            assert "No space left on device" in st.reason and not st.recording
            assert st.sources["daemon"]["error_counts"].get("recording") == 1
            n = d.frames_published
            assert wait_for(lambda: d.frames_published > n + 10), "the stream goes on"
            with pytest.raises(ControlError, match="No space left on device.*incomplete"):
                c.record_stop()
            assert wait_for(lambda: c.status().state == "running", 5.0)
    finally:
        d.stop()


def test_record_to_a_device_is_refused_at_start():
    with pytest.raises(DaemonError, match="not a regular file"):
        Daemon(
            fake_config(**{"recording.path": "/dev/full"}),
            camera=ScriptedCamera(),
            pressure=constant_pressure(),
            processor_factory=FakeProcessor,
        ).start()


def test_recording_path_that_cannot_work_is_refused_naming_the_key(tmp_path):
    """`[recording] path = "/etc/hostname/x.mcap"` was refused naming the path but not the key,
    unlike every other configuration error."""
    a_file = tmp_path / "hostname"
    a_file.write_text("myhost\n")
    with pytest.raises(DaemonError) as info:
        Daemon(
            fake_config(**{"recording.path": str(a_file / "x.mcap")}),
            camera=ScriptedCamera(),
            pressure=constant_pressure(),
            processor_factory=FakeProcessor,
        ).start()
    assert str(info.value).startswith("recording.path: cannot record: ")
    assert f"{a_file} is a file, not a folder" in str(info.value)


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


def test_record_start_creates_no_folders(tmp_path):
    d = start_daemon()
    try:
        with Controller(d.control_address) as c:
            with pytest.raises(ControlError, match="does not exist"):
                c.record_start(str(tmp_path / "a" / "b" / "x.mcap"))
        assert not (tmp_path / "a").exists()
    finally:
        d.stop()


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


# ================================================================== bad recordings
def damage_punyo(root: Path, kind: str) -> str:
    """Damage frame 1 of a punyo recording; returns the file name the error must name."""
    exp = root / "expand"
    if kind == "truncated_npy":
        data = (exp / "rgb_1.npy").read_bytes()
        (exp / "rgb_1.npy").write_bytes(data[: len(data) // 2])
        return "rgb_1.npy"
    if kind == "garbage_npy":
        (exp / "pc_1.npy").write_bytes(os.urandom(300))
        return "pc_1.npy"
    if kind == "small_image":
        np.save(exp / "rgb_1.npy", np.zeros((H // 2, W // 2, 3), np.uint8))
        return "rgb_1.npy"
    if kind == "float64_image":
        np.save(exp / "rgb_1.npy", np.zeros((H, W, 3), np.float64))
        return "rgb_1.npy"
    if kind == "all_nan_depth":
        np.save(exp / "pc_1.npy", np.full((H * W, 3), np.nan, np.float32))
        return "frame 1"
    if kind == "nan_pressure":
        np.save(exp / "pressure_1.npy", np.float64("nan"))
        return "pressure_1.npy"
    raise AssertionError(kind)


BAD_KINDS = [
    "truncated_npy",
    "garbage_npy",
    "small_image",
    "float64_image",
    "all_nan_depth",
    "nan_pressure",
]


@pytest.mark.parametrize("kind", BAD_KINDS)
def test_bad_punyo_frame_is_skipped_counted_and_named(tmp_path, kind):
    """One bad frame made the replay restart from frame 0 every 0.5 s, even with loop=false."""
    root = tmp_path / "rec"
    make_punyo(root, n=5)
    name = damage_punyo(root, kind)
    src = ReplayCamera(str(root), realtime=False, loop=False)
    d = start_daemon(src, **{"camera.pace": "fast", "camera.loop": False})
    try:
        assert wait_for(lambda: src.finished.is_set() and d.frames_published >= 1, 20)
        # Every good frame (4 of 5) went through, and the status says so.
        assert wait_for(lambda: status(d).sources[src.name]["received"] == 4, 20)
        st = status(d)
    finally:
        d.stop()
    stats = st.sources[src.name]
    assert stats["error_counts"] == {"bad_frame": 1}
    assert name in stats["last_error"] and "frame 1" in stats["last_error"]
    assert src.stats.received == 4 and len(src.bad_frames) == 1


def test_replay_with_a_bad_frame_never_restarts_from_frame_0(tmp_path):
    root = tmp_path / "rec"
    make_punyo(root, n=5)
    damage_punyo(root, "truncated_npy")
    src = ReplayCamera(str(root), realtime=True, loop=False)
    emitted: list[int] = []
    orig = src.emit
    src.emit = lambda f: (emitted.append(f.index), orig(f))  # type: ignore[method-assign]
    src.start()
    try:
        assert src.finished.wait(10)
        # Time is the subject: nothing may be emitted for longer than the old code's 0.5 s
        # restart period after the end.
        time.sleep(0.6)
    finally:
        src.stop()
    assert emitted == [0, 2, 3, 4]


def bad_mcap(p: Path) -> None:
    """An MCAP recording whose frames 1..4 are bad: truncated image data, a 12 x 16 image, all-NaN
    depth, NaN pressure."""
    rec = Recorder(p, CAM, queue_size=10000)
    for i in range(8):
        f = make_frame(i)
        t = 1000.0 + i / 30
        rgb = raw_image(f.rgb, t)
        depth = raw_image(f.depth, t)
        pressure = pb.PressureSample(time_ns=int(t * 1e9), pressure_pa=P0, frame_index=i)
        if i == 1:
            rgb.data = rgb.data[:100]
        elif i == 2:
            rgb = raw_image(np.zeros((12, 16, 3), np.uint8), t)
        elif i == 3:
            depth = raw_image(np.full((H, W), np.nan, np.float32), t)
        elif i == 4:
            pressure.pressure_pa = float("nan")
        rec.write_message(TOPIC_RGB, rgb, t, i)
        rec.write_message(TOPIC_DEPTH, depth, t, i)
        rec.write_message(TOPIC_PRESSURE, pressure, t, i)
    rec.close()


def test_bad_mcap_frames_are_skipped_counted_and_named(tmp_path):
    p = tmp_path / "bad.mcap"
    bad_mcap(p)
    src = ReplayCamera(str(p), realtime=False, loop=False)
    d = start_daemon(src, **{"camera.pace": "fast", "camera.loop": False, "reference.frames": 1})
    try:
        assert wait_for(lambda: src.finished.is_set() and d.frames_published >= 3, 20)
        st = status(d)
    finally:
        d.stop()
    stats = st.sources[src.name]
    assert stats["error_counts"] == {"bad_frame": 4}
    bad = list(src.bad_frames)
    assert [b.split(":")[0] for b in bad] == [f"bad.mcap frame {i}" for i in (1, 2, 3, 4)]
    assert "cannot reshape array of size 100" in bad[0] and "16 x 12" in bad[1]
    assert "no valid pixel" in bad[2] and "not finite" in bad[3]
    assert src.stats.received == 4


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


def test_truncated_rgb_0_npy_gives_a_clear_error(tmp_path):
    """Used to exit with a bare `mmap length is greater than file size` traceback."""
    root = tmp_path / "rec"
    make_punyo(root, n=3)
    f = root / "expand" / "rgb_0.npy"
    f.write_bytes(f.read_bytes()[:200])
    with pytest.raises(FrameError, match=r"rgb_0\.npy: unreadable, damaged or truncated"):
        open_recording(root)
    with pytest.raises(SourceError, match=r"rgb_0\.npy"):
        ReplayCamera(str(root))
    from bubble_rt.cli import main

    assert main(["serve", "--camera", f"replay:{root}", "--duration", "0.1"]) == 1


# ================================================================== control
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


def test_parameter_ranges_are_the_configurations():
    for name in PARAM_NAMES:
        r = ESTIMATOR_RANGES[name]
        for bad in (r.lo - abs(r.lo) - 1, r.hi * 10):
            with pytest.raises(ConfigError, match=f"estimator.{name}: must be in"):
                DaemonConfig.from_dict({"estimator": {name: bad}})
            from bubble_rt.daemon.control import validate_params

            assert validate_params({name: bad}) == (f"set_params: {name} {r.problem(bad)}")
        DaemonConfig.from_dict({"estimator": {name: r.lo}})
        DaemonConfig.from_dict({"estimator": {name: r.hi}})


def test_estimator_is_finite_at_every_range_limit():
    """The ranges keep the solve regular: both ends of each give solved, finite forces."""
    from bubble_rt.estimation.estimator import ForceEstimator
    from bubble_rt.estimation.membrane import Material
    from bubble_rt.mesh import Mesh

    mesh = Mesh.preset("coarse")
    V = mesh.vertices
    U = np.zeros_like(V)
    U[:, 2] = -8e-3 * np.exp(-((np.linalg.norm(V[:, :2] - [0.01, 0.005], axis=1) / 0.015) ** 2))
    U[mesh.boundary] = 0.0
    for name in PARAM_NAMES:
        for v in (ESTIMATOR_RANGES[name].lo, ESTIMATOR_RANGES[name].hi):
            est = ForceEstimator(mesh)
            est.reconfigure(
                **(
                    {"material": Material(E=v, nu=0.5, thickness=0.65e-3)}
                    if name == "youngs_modulus"
                    else {name: v}
                )
            )
            e = est.estimate(U, 320.0)
            assert e.info.status == "solved", (name, v)
            assert np.isfinite(e.node_forces).all(), (name, v)


class NonFiniteProcessor(FakeProcessor):
    def stage2(self, frame, data):  # type: ignore[no-untyped-def]
        est = super().stage2(frame, data)
        est.info = SimpleNamespace(**{**vars(est.info), "status": "non_finite_input"})
        est.node_forces = np.zeros_like(est.node_forces)
        return est


def test_solver_status_other_than_solved_marks_the_frame_degraded():
    """k_f=1e308 gave zero forces with non_finite_input, yet degraded=false."""
    from bubble_rt.io.client import Subscriber

    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(),
        pressure=constant_pressure(),
        processor_factory=NonFiniteProcessor,
    ).start()
    try:
        with Subscriber(d.pub_address, d.control_address, timeout_s=10) as sub:
            frames = list(sub.frames(count=3, timeout_s=10))
        assert frames and all(f.degraded for f in frames)
        assert all("solver status non_finite_input" in " ".join(f.degraded_reasons) for f in frames)
        st = status(d)
        assert st.state == "degraded" and "non_finite_input" in st.reason
    finally:
        d.stop()


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
            assert c.status().state == "running"
    finally:
        d.stop()


# ================================================================== smaller
def test_reference_pressure_comes_from_the_pressure_source_in_use():
    """Sim camera + serial sensor: dp was about -5,000 Pa throughout."""
    sensor = 101_325.0
    buf = PressureBuffer()
    stop = threading.Event()

    def serial_like() -> None:
        # Time is the scenario: a 100 Hz sensor whose readings start 0.3 s after the daemon.
        stop.wait(0.3)
        while not stop.is_set():
            buf.push(time.time(), sensor)
            stop.wait(0.01)

    th = threading.Thread(target=serial_like, daemon=True)
    th.start()
    d = Daemon(
        fake_config(),
        camera=sim_like_camera(pressure_pa=96_000.0),
        pressure=(buf, None),
        processor_factory=FakeProcessor,
    ).start()
    try:
        assert d.wait_ready(20)
        assert d.processor.reference.pressure_pa == pytest.approx(sensor)
        from bubble_rt.io.client import Subscriber

        with Subscriber(d.pub_address, d.control_address, timeout_s=10) as sub:
            frames = list(sub.frames(count=5, timeout_s=10))
        assert all(abs(f.pressure_delta_pa) < 1.0 for f in frames)
    finally:
        stop.set()
        d.stop()


def test_status_counts_faults_per_kind():
    """The README says faults are counted per kind in the status; only totals were sent."""
    cam = ScriptedCamera()
    d = start_daemon(cam)
    try:
        cam.fail_next.set()
        assert wait_for(lambda: cam.stats.errors.get("disconnected") == 1)
        d._error("estimator", "boom")
        d._error("estimator", "boom")
        st = status(d)
    finally:
        d.stop()
    assert st.sources["scripted"]["error_counts"] == {"disconnected": 1}
    assert st.sources["scripted"]["errors"] == 1
    assert st.sources["daemon"]["error_counts"] == {"estimator": 2}


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
