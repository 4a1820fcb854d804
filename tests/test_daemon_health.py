"""bubble_rt.daemon.health: the daemon's state and its reason (running, degraded by a stalled
or unplugged camera or stale pressure), in get_status and on the status topic."""

from __future__ import annotations

import logging
import time

import pytest
from bubble_rt.daemon.service import Daemon
from bubble_rt.io import protocol
from bubble_rt.io.client import Controller, Subscriber
from daemon_fakes import (
    FakeProcessor,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    feed_reference_and_first_frame,
    start,
    start_fed,
    status_of,
)
from waiting import wait_for

pytestmark = pytest.mark.timeout(60)


def test_status_running_then_stopped(daemon):
    d, _ = daemon
    assert wait_for(lambda: status_of(d).state == "running")
    st = status_of(d)
    assert st.frames_published > 0 and st.latency_p99_ms >= st.latency_p50_ms > 0
    assert "scripted" in st.sources


def test_camera_stall_degrades_then_resumes(daemon):
    d, cam = daemon
    assert wait_for(lambda: status_of(d).state == "running")
    cam.pause.set()
    assert wait_for(lambda: status_of(d).state == "degraded")
    assert "camera stalled" in status_of(d).reason
    n = d.frames_published
    cam.pause.clear()
    assert wait_for(lambda: status_of(d).state == "running")
    # "running" returns with the camera's first frame, before the estimator publishes it
    assert wait_for(lambda: d.frames_published > n)


def test_camera_disconnect_reports_and_recovers(daemon):
    d, cam = daemon
    cam.fail_next.set()
    assert wait_for(lambda: cam.sessions >= 2)
    assert cam.stats.errors.get("disconnected") == 1
    assert "device unplugged" in cam.stats.last_error
    n = d.frames_published
    assert wait_for(lambda: d.frames_published > n + 5)


def test_status_topic_reports_degraded_reason(daemon):
    d, cam = daemon
    cam.pause.set()
    with Subscriber(d.pub_address, d.control_address) as sub:
        end = time.monotonic() + 5
        st = None
        while time.monotonic() < end:
            m = sub.recv(0.5)
            if isinstance(m, protocol.StatusData) and m.state == "degraded":
                st = m
                break
    assert st is not None and "camera stalled" in st.reason


def test_stale_pressure_marks_frames_degraded():
    from bubble_rt.daemon.sources import PressureBuffer

    buf = PressureBuffer(16)
    buf.push(time.time() - 10.0, 101325.0)
    cam = ScriptedCamera()
    d = Daemon(
        fake_config(), camera=cam, pressure=(buf, None), processor_factory=FakeProcessor
    ).start()
    try:
        assert d.wait_ready(10)
        with Subscriber(d.pub_address, d.control_address) as sub:
            f = next(sub.frames(count=1, timeout_s=5))
        assert f.degraded and "pressure stale" in f.degraded_reasons[0]
        assert wait_for(lambda: "pressure stale" in status_of(d).reason)
    finally:
        d.stop()


class FailingProcessor(FakeProcessor):
    """Every frame fails in stage one (a source that keeps producing unusable frames)."""

    def stage1(self, frame):  # type: ignore[no-untyped-def]
        raise ValueError("frame unusable: no valid depth")


@pytest.mark.timeout(240)
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


def test_a_new_reason_is_published_before_the_status_period_ends():
    # A status period far longer than the test: only the reason's own refresh can publish the
    # stall's growing age (and the reference capture's progress) while the state stays the same.
    d, cam = start(fake_config(**{"network.status_period_s": 60.0}))
    try:
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert wait_for(lambda: isinstance(sub.recv(0.5), protocol.ForceFrameData))
            cam.pause.set()
            reasons: list[str] = []

            def two_stall_reasons() -> bool:
                m = sub.recv(0.1)
                if isinstance(m, protocol.StatusData) and m.state == "degraded":
                    reasons.append(m.reason)
                return len(set(reasons)) >= 2

            assert wait_for(two_stall_reasons, timeout=5.0)
        assert all("camera stalled" in r for r in reasons), reasons
    finally:
        d.stop()


def test_running_reaches_a_subscriber_before_the_first_force_frame():
    # The status went out from the control loop up to 50 ms after the first force frame, so a
    # subscriber (`bubble-rt echo`) showed its first frames as "starting".
    d, cam = start_fed()
    try:
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert wait_for(lambda: isinstance(sub.recv(0.2), protocol.StatusData))
            states: list[str] = []

            def first_force_frame() -> bool:
                m = sub.recv(0.2)
                if isinstance(m, protocol.StatusData):
                    states.append(m.state)
                return isinstance(m, protocol.ForceFrameData)

            feed_reference_and_first_frame(d, cam)
            assert wait_for(first_force_frame)
        assert states and states[-1] == "running", states
    finally:
        cam.close()
        d.stop()
