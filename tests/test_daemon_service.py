"""bubble_rt.daemon.service: the pipeline publishes frames with the mesh, timings and patches;
slow subscribers, late subscribers, a port in use, single-stage processing, drops counted
(a fake camera and processor)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
import zmq
from bubble_rt.daemon.service import Daemon, DaemonError
from bubble_rt.frames import Frame
from bubble_rt.io.client import Subscriber
from daemon_fakes import (
    FakeProcessor,
    Published,
    ScriptedCamera,
    constant_pressure,
    fake_config,
    feed_reference_and_first_frame,
    make_frame,
    refused_at_load,
    start,
    start_daemon,
    start_fed,
    status_of,
)
from waiting import wait_for

pytestmark = pytest.mark.timeout(60)


def test_frames_flow_with_mesh_and_timings(daemon):
    d, _ = daemon
    with Subscriber(d.pub_address, d.control_address) as sub:
        mesh = sub.mesh
        frames = list(sub.frames(count=5, timeout_s=5))
    assert len(frames) == 5
    assert mesh.n_nodes == 227 and mesh.vertices.shape == (227, 3)
    f = frames[-1]
    assert f.mesh_id == mesh.mesh_id
    assert f.node_forces.shape == (227, 3) and f.contact.shape == (227,)
    assert f.net_force[2] < 0
    np.testing.assert_allclose(f.net_force, f.node_forces.sum(axis=0))
    assert len(f.patches) == 1 and f.patches[0].area > 0
    assert {"wait", "stage1", "queue", "solve", "stage2"} <= set(f.timings_ms)
    assert f.latency_ms > 0 and f.publish_time_ns >= f.capture_time_ns
    assert [x.seq for x in frames] == sorted(x.seq for x in frames)
    assert f.solver_status == "solved"


def test_opencv_threads_setting_reaches_opencv():
    """``processing.opencv_threads`` sets OpenCV's thread count (cv::setNumThreads). Debian's
    OpenCV runs its parallel loops on TBB, which ignored the OPENCV_FOR_THREADS_NUM the daemon
    used to set: its flow ran on both cores whatever the setting."""
    from bubble_rt import _core

    before = _core._opencv_threads()
    try:
        _core._set_opencv_threads(3)
        d = start_daemon(**{"processing.opencv_threads": 1})
        try:
            assert _core._opencv_threads() == 1
        finally:
            d.stop()
    finally:
        _core._set_opencv_threads(before)


def test_slow_subscriber_does_not_block_publishing():
    cfg = fake_config(**{"network.sndhwm": 2})
    # 50 Hz leaves the fast reader 20 ms a frame: enough on a loaded 2-core machine, where at
    # 200 Hz the fast reader itself sometimes fell two frames behind.
    d, _ = start(cfg, camera=ScriptedCamera(rate_hz=50.0))
    try:
        ctx = zmq.Context.instance()
        slow = ctx.socket(zmq.SUB)
        slow.setsockopt(zmq.RCVHWM, 1)
        slow.setsockopt(zmq.RCVBUF, 4096)
        slow.setsockopt(zmq.SUBSCRIBE, b"")
        slow.connect(d.pub_address)
        with Subscriber(d.pub_address, d.control_address) as fast:
            frames = list(fast.frames(count=150, timeout_s=5))
        slow.close(linger=0)
        assert len(frames) == 150
        seqs = [f.seq for f in frames]
        # The fast subscriber saw consecutive frames although the slow one never read.
        assert seqs == list(range(seqs[0], seqs[0] + 150))
    finally:
        d.stop()


def test_late_subscriber_gets_mesh_and_next_frame(daemon):
    d, _ = daemon
    assert wait_for(lambda: d.frames_published > 20)
    with Subscriber(d.pub_address, d.control_address) as sub:
        mesh = sub.mesh
        frame = next(sub.frames(count=1, timeout_s=5))
    assert frame.seq >= 20 and frame.mesh_id == mesh.mesh_id
    assert frame.node_forces.shape[0] == mesh.n_nodes


def test_port_in_use_is_a_clear_error(daemon):
    d, _ = daemon
    cfg = fake_config(**{"network.pub": d.pub_address})
    with pytest.raises(DaemonError, match="cannot bind network.pub"):
        Daemon(
            cfg,
            camera=ScriptedCamera(),
            pressure=constant_pressure(),
            processor_factory=FakeProcessor,
        ).start()


def test_single_stage_pipeline_publishes():
    d, _ = start(fake_config(**{"processing.pipeline": "single"}))
    try:
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert len(list(sub.frames(count=3, timeout_s=5))) == 3
    finally:
        d.stop()


def test_drops_are_counted_when_processing_is_slow():
    d, _ = start(camera=ScriptedCamera(rate_hz=200.0))
    try:
        FakeProcessor.instances[-1].delay_s = 0.05
        assert wait_for(lambda: d.frames_dropped > 10)
        assert wait_for(lambda: status_of(d).frames_dropped > 10)
    finally:
        d.stop()


@pytest.mark.timeout(240)
def test_huge_shutdown_timeout_is_refused_and_the_largest_stops_in_time():
    e = refused_at_load("shutdown_timeout_s", 1e300)
    assert e.key == "shutdown_timeout_s" and "[0.1, 600] s" in str(e)
    cfg = fake_config(shutdown_timeout_s=600.0)
    d = Daemon(
        cfg, camera=ScriptedCamera(), pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    assert d.wait_ready(20)
    # No OverflowError, and stop returns with every thread ended (waiting out the 600 s
    # timeout would hit this test's own timeout).
    d.stop()
    assert d.alive_threads() == []


class SlowToBuildProcessor(FakeProcessor):
    """A FakeProcessor whose construction (the estimator build) takes 0.6 s."""

    def __init__(self, *args, **kwargs):
        threading.Event().wait(0.6)
        super().__init__(*args, **kwargs)


def test_frames_replaced_before_the_reference_are_not_drops():
    # 100 Hz camera while the processor builds for 0.6 s: ~60 frames replaced in the slot
    # before the estimator exists. They are not "dropped": only frames it could have processed.
    cam = ScriptedCamera(rate_hz=100.0)
    d = Daemon(
        fake_config(),
        camera=cam,
        pressure=constant_pressure(),
        processor_factory=SlowToBuildProcessor,
    ).start()
    try:
        assert d.frames_dropped == 0
        assert d.wait_ready(20.0)
        assert d.vitals.drops_not_counted >= 30  # the frames were replaced
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert len(list(sub.frames(count=10, timeout_s=5))) == 10
        assert d.frames_dropped < 15
        assert status_of(d).frames_dropped < 15
    finally:
        d.stop()


class SlowToTareProcessor(FakeProcessor):
    """A FakeProcessor whose tare (the estimator rebuilt on the new reference) takes 0.6 s."""

    def set_reference(self, frames: list[Frame]) -> None:
        threading.Event().wait(0.6)
        super().set_reference(frames)


def test_frames_replaced_while_a_tare_rebuilds_the_estimator_are_not_drops():
    # 100 Hz camera while the tare rebuilds for 0.6 s: ~60 frames replaced in the slot that no
    # estimator could take. Counted apart, not as drops; the frames before and after still are.
    d = Daemon(
        fake_config(),
        camera=ScriptedCamera(rate_hz=100.0),
        pressure=constant_pressure(),
        processor_factory=SlowToTareProcessor,
    ).start()
    try:
        assert d.wait_ready(20.0)
        proc = FakeProcessor.instances[-1]
        uncounted = d.vitals.drops_not_counted
        d.request_tare()
        assert wait_for(lambda: proc.references == 2 and not d.tare_pending, timeout=10)
        assert d.vitals.drops_not_counted - uncounted >= 30  # the frames were replaced
        with Subscriber(d.pub_address, d.control_address) as sub:
            assert len(list(sub.frames(count=10, timeout_s=5))) == 10
        assert d.frames_dropped < 15
        # Still counted once the estimator is back: a slow solve drops frames again.
        proc.delay_s = 0.05
        assert wait_for(lambda: d.frames_dropped > 15)
    finally:
        d.stop()


class _HeldProcessor(FakeProcessor):
    """A FakeProcessor whose stage two waits at ``hold`` (once ``armed``) until ``release``."""

    def __init__(self, *a: Any) -> None:
        super().__init__(*a)
        self.armed, self.held, self.release = (
            threading.Event(),
            threading.Event(),
            threading.Event(),
        )

    def stage2(self, frame: Frame, data: Any) -> Any:
        if self.armed.is_set() and not self.release.is_set():
            self.held.set()
            self.release.wait(10.0)
        return super().stage2(frame, data)


def test_one_slow_solve_delays_the_next_frames_instead_of_dropping_them():
    # Frames fed one by one: the camera, stage one and stage two are gated, so this is the
    # same on any machine. While stage two is held on frame B, frames C and D pass stage one
    # and wait; once it is released all of them are published and nothing is dropped.
    d, cam = start_fed(_HeldProcessor)
    try:
        feed_reference_and_first_frame(d, cam)
        proc = FakeProcessor.instances[-1]
        assert isinstance(proc, _HeldProcessor)
        proc.armed.set()
        cam.feed(make_frame(3))  # B: stage two holds it
        assert wait_for(proc.held.is_set)
        put_before = d.stage_queue.put_count
        cam.feed(make_frame(4))  # C
        cam.feed(make_frame(5))  # D
        assert wait_for(lambda: d.stage_queue.put_count == put_before + 2)
        proc.release.set()
        assert wait_for(lambda: d.frames_published == 4)
        assert d.frames_dropped == 0
    finally:
        for p in FakeProcessor.instances:
            if isinstance(p, _HeldProcessor):
                p.release.set()
        cam.close()
        d.stop()


class _SlowBuild(FakeProcessor):
    """A FakeProcessor whose construction (the estimator's build) waits for ``go``."""

    building = threading.Event()
    go = threading.Event()

    def __init__(self, *a: Any) -> None:
        _SlowBuild.building.set()
        assert _SlowBuild.go.wait(10.0)
        super().__init__(*a)


def test_frames_that_waited_for_the_estimator_give_way_to_the_newest():
    # Two frames arrive while the estimator is built: the first force frame is the newer one
    # (a backlog made the first frames 50-100 ms late), and neither counts as dropped.
    _SlowBuild.building.clear()
    _SlowBuild.go.clear()
    d, cam = start_fed(_SlowBuild)
    seen = Published()
    d.viewers.append(seen)
    try:
        cam.feed(make_frame(0))
        assert wait_for(lambda: len(d.reference_collected) == 1)
        cam.feed(make_frame(1))
        assert wait_for(_SlowBuild.building.is_set)
        cam.feed(make_frame(2))
        cam.feed(make_frame(3))
        assert wait_for(lambda: cam.output.put_count == 4)
        _SlowBuild.go.set()
        assert wait_for(lambda: d.frames_published >= 1)
        cam.feed(make_frame(4))
        assert wait_for(lambda: 4 in seen.fz)
        assert list(seen.fz) == [3, 4] and d.frames_dropped == 0
    finally:
        _SlowBuild.go.set()
        cam.close()
        d.stop()
