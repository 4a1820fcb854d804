"""bubble_rt.daemon.faults: what goes wrong while the daemon runs is contained and reported:
a recording that fails or cannot start (the key named), simulated reference frames on the
daemon clock, a solver status other than solved, the reference pressure from the source in
use, fault counts per kind in the status."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from bubble_rt.daemon.service import Daemon, DaemonError
from bubble_rt.daemon.sources import PressureBuffer
from bubble_rt.io.client import ControlError, Controller
from bubble_rt.io.mcap import McapRecording
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    sim_like_camera,
    start_daemon,
)
from daemon_fakes import status_of as status
from recording_fakes import log_times
from waiting import wait_for

pytestmark = pytest.mark.timeout(120)


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


def test_daemon_recording_failure_turns_status_to_error_and_stream_goes_on(monkeypatch, tmp_path):
    import bubble_rt.io.mcap_writer as mcap_mod

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
    """docs/daemon.md says faults are counted per kind in the status; only totals were sent."""
    cam = ScriptedCamera()
    d = start_daemon(cam)
    try:
        cam.fail_next.set()
        assert wait_for(lambda: cam.stats.errors.get("disconnected") == 1)
        d.report_error("estimator", "boom")
        d.report_error("estimator", "boom")
        st = status(d)
    finally:
        d.stop()
    assert st.sources["scripted"]["error_counts"] == {"disconnected": 1}
    assert st.sources["scripted"]["errors"] == 1
    assert st.sources["daemon"]["error_counts"] == {"estimator": 2}
