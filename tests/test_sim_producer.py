"""The simulated camera's renderer process (bubble_rt.daemon.sim_producer): its wire format,
that its frames equal the simulator's, and that it never outlives the daemon (SIGINT, SIGTERM,
--duration, the daemon killed)."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.daemon.sim_wire import (
    frame_message,
    message_frame,
    read_message,
    write_message,
)
from bubble_rt.io.client import Subscriber
from daemon_fakes import make_frame
from waiting import ANY_PORT, ServedProcess, wait_for

pytestmark = pytest.mark.timeout(120)
TESTS = Path(__file__).resolve().parent


def test_frame_round_trips_through_the_wire_format():
    f = make_frame(7, push=2.0)
    f.meta["reference"] = True
    buf = io.BytesIO()
    fields, arrays = frame_message(f)
    write_message(buf, "frame", arrays, **fields)
    write_message(buf, "pass_end")
    buf.seek(0)
    header, got = read_message(buf)  # type: ignore[misc]
    g = message_frame(header, got, truth=None)
    assert header["kind"] == "frame" and g.index == 7 and g.t == f.t
    assert np.array_equal(g.rgb, f.rgb) and np.array_equal(g.depth, f.depth)
    assert g.pressure_pa == f.pressure_pa and g.meta == f.meta
    assert read_message(buf)[0]["kind"] == "pass_end"  # type: ignore[index]
    assert read_message(buf) is None  # end of stream


def test_truncated_message_reads_as_end_of_stream():
    buf = io.BytesIO()
    fields, arrays = frame_message(make_frame(1))
    write_message(buf, "frame", arrays, **fields)
    cut = io.BytesIO(buf.getvalue()[:-100])
    assert read_message(cut) is None


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(c) for c in text]
    return out


def _gone(pid: int, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return True
        if state == "Z":  # exited, not yet reaped by its (dead) parent's reaper
            return True
        time.sleep(0.05)
    return False


def _serve(*extra: str) -> tuple[subprocess.Popen, str, str]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS)] + [p for p in sys.path if p])
    served = ServedProcess(
        [sys.executable, str(TESTS / "daemon_fakes.py"), "--sim", "--pub", ANY_PORT]
        + ["--control", ANY_PORT, *extra],
        env=env,
    )
    pub, ctl = served.addresses(60)  # the endpoints it bound (any free port)
    return served.proc, pub, ctl


def _producer_of(proc: subprocess.Popen, pub: str, ctl: str) -> int:
    with Subscriber(pub, ctl, timeout_s=60) as sub:
        assert len(list(sub.frames(count=5, timeout_s=60))) == 5
    (child,) = _children(proc.pid)  # the renderer process
    cmd = Path(f"/proc/{child}/cmdline").read_bytes()
    assert b"bubble_rt.daemon.sim_producer" in cmd
    return child


@pytest.mark.parametrize("how", ["sigint", "sigterm", "duration", "sigkill"], ids=lambda s: str(s))
def test_renderer_process_never_outlives_the_daemon(how):
    proc, pub, ctl = _serve(*(["--duration", "4"] if how == "duration" else []))
    try:
        child = _producer_of(proc, pub, ctl)
        if how != "duration":
            sig = {"sigint": signal.SIGINT, "sigterm": signal.SIGTERM, "sigkill": signal.SIGKILL}
            proc.send_signal(sig[how])
        proc.wait(timeout=10.0)
        assert _gone(child), f"renderer process {child} still running after the daemon ended"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if how != "sigkill":
        assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""


def test_reference_frames_rendered_in_the_process_or_cached_equal_the_simulators(
    tmp_path, monkeypatch, caplog
):
    import logging
    import threading

    from bubble_rt.daemon.sim_cache import reference_cache_path
    from bubble_rt.daemon.sim_camera import SimCamera
    from bubble_rt.sim import Simulator
    from sim_recordings import TINY_SCENE

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    stop = threading.Event()
    caplog.set_level(logging.INFO, logger="bubble_rt.daemon.sources")
    got = {}
    for attempt in ("rendered by the child", "read from the cache"):
        cam = SimCamera(str(scene))
        try:
            got[attempt] = cam.producer.reference_frames(3, stop)
        finally:
            cam.stop()
        path = reference_cache_path(cam.producer.sim, 3)
        assert path is not None
        assert wait_for(path.exists, 10, "the reference cache (written in the background)")
    assert cam.producer.frames_received == 0  # the second camera rendered nothing
    # The cold cache: the renderer process computed the physics, with progress and its time.
    assert "simulating the physics of scene" in caplog.text
    assert "simulated in" in caplog.text
    want = Simulator(str(scene)).reference_frames(3)
    for attempt, frames in got.items():
        assert len(frames) == 3, attempt
        for g, w in zip(frames, want, strict=True):
            assert np.array_equal(g.rgb, w.rgb) and np.array_equal(g.depth, w.depth), attempt
            assert g.pressure_pa == w.pressure_pa and g.t == w.t, attempt
            assert g.truth.pressure_pa == w.truth.pressure_pa, attempt


def test_a_pass_stored_on_disk_replays_the_same_frames_without_rendering(tmp_path, monkeypatch):
    from bubble_rt.daemon.sim_cache import pass_cache_path
    from bubble_rt.daemon.sim_camera import SimCamera
    from sim_recordings import TINY_SCENE

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)

    def first_frames(cam, n):  # type: ignore[no-untyped-def]
        cam.prepare()
        cam.start()
        try:
            return [cam.output.get(60.0) for _ in range(n)]
        finally:
            cam.stop()

    cam = SimCamera(str(scene), lossless=True)
    assert cam.cached_pass is None
    rendered = first_frames(cam, 8)  # a whole pass (6) and the start of the replay
    path = pass_cache_path(cam.producer.sim)
    assert path is not None
    assert wait_for(path.exists, 20, "the pass cache (written in the background)")
    again = SimCamera(str(scene), lossless=True)
    assert again.cached_pass is not None and len(again.cached_pass) == 6
    replayed = first_frames(again, 8)
    assert again.producer.frames_received == 0  # nothing rendered
    for r, g in zip(rendered, replayed, strict=True):
        assert r.index == g.index
        assert np.array_equal(r.rgb, g.rgb) and np.array_equal(r.depth, g.depth)
        assert r.pressure_pa == g.pressure_pa
        assert np.allclose(r.truth.net_force, g.truth.net_force)


def test_a_pass_cut_short_by_a_stop_is_never_stored_and_a_partial_one_is_ignored(
    tmp_path, monkeypatch
):
    """A daemon stopped mid-pass must not leave a part of a pass in the cache: replayed, it
    would loop over the scene's first frames only (the demo never pressing)."""
    from bubble_rt.daemon.sim_cache import load_pass, pass_cache_path, store_pass
    from bubble_rt.daemon.sim_camera import SimCamera
    from sim_recordings import TINY_SCENE

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    cam = SimCamera(str(scene), lossless=True)
    cam.prepare()
    cam.start()
    try:
        part = [cam.output.get(60.0) for _ in range(3)]  # half of the 6-frame pass
    finally:
        cam.stop()
    path = pass_cache_path(cam.producer.sim)
    assert path is not None and all(f is not None for f in part)
    time.sleep(1.0)  # the store would run in a background thread: give it the chance
    assert not path.exists()
    store_pass(path, part)  # a partial pass written by an older version
    assert path.exists() and load_pass(path, 6) is None
    assert SimCamera(str(scene), lossless=True).cached_pass is None


@pytest.mark.parametrize("profile", ["sim", "punyo"])
def test_sim_camera_reads_as_its_scenes_sensor_profile(tmp_path, monkeypatch, profile):
    # A simulated Punyo is Punyo hardware to the estimator: with the "sim" profile's ambient
    # pressure the daemon read 0.65 of its true force (serve --camera sim:punyo).
    from bubble_rt.config import DaemonConfig
    from bubble_rt.daemon.sim_camera import SimCamera
    from bubble_rt.daemon.startup import resolve_profile
    from bubble_rt.sensor import PROFILES
    from sim_recordings import TINY_SCENE

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / f"{profile}.toml"
    scene.write_text(f'profile = "{profile}"\n' + TINY_SCENE)
    cam = SimCamera(str(scene))
    try:
        est = resolve_profile(DaemonConfig(), cam.layout).estimator
        assert cam.layout == profile and est.profile == profile
        assert est.ambient_pa == PROFILES[profile].ambient_pa
    finally:
        cam.stop()
