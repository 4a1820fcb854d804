"""Small fakes for the daemon tests: a scripted camera and a processor without the estimator."""

from __future__ import annotations

import os
import queue
import threading
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.config import ConfigError, DaemonConfig
from bubble_rt.daemon.service import Daemon
from bubble_rt.daemon.sources import ConstantPressure, IterableCamera
from bubble_rt.estimation.solver import SolverInfo
from bubble_rt.estimation.types import Estimate
from bubble_rt.frames import Frame
from bubble_rt.io.client import Controller
from bubble_rt.mesh import Mesh
from waiting import ANY_PORT, wait_for

H, W = 24, 32
P0 = 101325.0
_MESH: dict[str, Mesh] = {}


def coarse_mesh() -> Mesh:
    if "m" not in _MESH:
        _MESH["m"] = Mesh.preset("coarse")
    return _MESH["m"]


def fake_config(**overrides: Any) -> DaemonConfig:
    base = {
        # Any free port: the daemon binds it and names it (Daemon.pub_address, .control_address).
        "network.pub": ANY_PORT,
        "network.control": ANY_PORT,
        "network.status_period_s": 0.2,
        "reference.frames": 3,
        "camera.stall_timeout_s": 0.3,
    }
    base.update(overrides)
    return DaemonConfig().with_overrides(**base)


def status_of(d: Any) -> Any:
    """The running daemon ``d``'s status, asked over its control socket."""
    with Controller(d.control_address) as c:
        return c.status()


def make_frame(i: int, push: float = 0.0) -> Frame:
    """A tiny synthetic frame; ``push`` (N) is what the fake processor reports as net force."""
    rgb = np.full((H, W, 3), i % 255, np.uint8)
    depth = np.full((H, W), 0.07, np.float32)
    return Frame(
        rgb=rgb, depth=depth, pressure_pa=P0 + 10.0 * push, t=i / 30.0, index=i, meta={"push": push}
    )


class ScriptedCamera(IterableCamera):
    """Endless synthetic frames; ``pause`` stalls it, ``fail_next`` makes it raise once."""

    def __init__(self, rate_hz: float | None = 100.0, lossless: bool = False) -> None:
        self.pause = threading.Event()
        self.fail_next = threading.Event()
        self.sessions = 0
        super().__init__(
            self._gen,
            Camera.d405(width=W, height=H, cx=W / 2, cy=H / 2),
            rate_hz=rate_hz,
            lossless=lossless,
        )
        self.retry_s = 0.05
        self.name = self.stats.name = "scripted"

    def _gen(self):  # type: ignore[no-untyped-def]
        self.sessions += 1
        i = 0
        while not self._stop.is_set():
            while self.pause.is_set() and not self._stop.is_set():
                self._stop.wait(0.01)
            if self.fail_next.is_set():
                self.fail_next.clear()
                raise RuntimeError("device unplugged")
            yield make_frame(i, push=1.0 + (i % 3))
            i += 1


class FakeProcessor:
    """Force = (rgb[0, 0, 0] mod 5) + 1 newtons along -z on the first 5 interior nodes."""

    instances: list[FakeProcessor] = []

    def __init__(self, config: DaemonConfig, camera: Camera, frames: list[Frame]) -> None:
        self.mesh = coarse_mesh()
        self.reference = SimpleNamespace(
            pressure_pa=float(np.mean([f.pressure_pa for f in frames]))
        )
        self.params: dict[str, float] = {}
        self.references = 1
        self.nodes = np.flatnonzero(self.mesh.interior)[:5]
        self.delay_s = 0.0
        FakeProcessor.instances.append(self)

    def stage1(self, frame: Frame) -> Any:
        # Derived from the image so that a recording replays to the same outputs.
        return float(frame.rgb[0, 0, 0] % 5) + 1.0 if frame.rgb is not None else 0.0

    def stage2(self, frame: Frame, data: Any) -> Any:
        if self.delay_s:
            threading.Event().wait(self.delay_s)
        n = self.mesh.n_nodes
        f = np.zeros((n, 3))
        f[self.nodes, 2] = -data / len(self.nodes)
        contact = np.zeros(n, bool)
        contact[self.nodes] = True
        pressure = np.where(contact, 5000.0, 0.0)
        return Estimate(
            node_forces=f,
            contact_pressure=pressure[:, None] * np.array([0.0, 0.0, 1.0]),
            normal_pressure=pressure,
            contact=contact,
            net_force=f.sum(axis=0),
            displacements=np.zeros((n, 3)),
            info=SolverInfo(
                status="solved",
                iterations=3,
                primal_residual=1e-6,
                dual_residual=1e-6,
                objective=1.0,
            ),
            timings_ms={"solve": 0.1, "post": 0.01},
            pressure_delta_pa=float(frame.pressure_pa) - self.reference.pressure_pa,
        )

    def cold_start(self) -> None:
        """Nothing to reset: the fake keeps no solver state."""

    def set_reference(self, frames: list[Frame]) -> None:
        self.references += 1

    def reconfigure(self, params: dict[str, float]) -> None:
        self.params.update(params)


class FakeSensor:
    """The microcontroller side of a pseudo-terminal, behind a symlink that can be re-pointed."""

    def __init__(self, link: str) -> None:
        self.link = link
        self.open()

    def open(self) -> None:
        import tty

        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        if os.path.lexists(self.link):
            os.unlink(self.link)
        os.symlink(os.ttyname(self.slave), self.link)

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def unread(self) -> int:
        """Bytes written that the port's reader has not read yet (the tty's input queue)."""
        import fcntl
        import struct
        import termios

        return int(struct.unpack("i", fcntl.ioctl(self.slave, termios.FIONREAD, b"\0" * 4))[0])

    def vanish(self) -> None:
        os.close(self.master)
        os.close(self.slave)


class FakeSimulator:
    """The ``bubble_rt.sim.Simulator`` interface the sim source uses: a 4-frame scene of
    ``make_frame`` frames (``SimCamera(simulator="daemon_fakes:FakeSimulator")``; it runs in
    the sim source's renderer process, which imports it by that name)."""

    def __init__(self, scene: str, progress: Any = None) -> None:
        from types import SimpleNamespace

        self.scene = SimpleNamespace(frames=4, rates=SimpleNamespace(camera_hz=30.0))
        self.camera = Camera.d405(width=W, height=H, cx=W / 2, cy=H / 2)

    def frames(self):  # type: ignore[no-untyped-def]
        for i in range(4):
            yield make_frame(i)

    def reference_frames(self, n: int) -> list[Frame]:
        return [make_frame(-n + k) for k in range(n)]


def constant_pressure() -> tuple[ConstantPressure, None]:
    return ConstantPressure(P0), None


def start(
    cfg: DaemonConfig | None = None, camera: Any = None, pressure: Any = None, **kw: Any
) -> tuple[Daemon, Any]:
    """A started daemon on the fakes (``fake_config()`` unless ``cfg``; a ScriptedCamera and a
    constant pressure unless given), ready, and its camera."""
    cam = camera or ScriptedCamera()
    d = Daemon(
        cfg or fake_config(),
        camera=cam,
        pressure=pressure or constant_pressure(),
        processor_factory=FakeProcessor,
        **kw,
    ).start()
    assert d.wait_ready(20.0)
    return d, cam


def nested(dotted: str, value: Any) -> dict[str, Any]:
    """``{"section": {"key": value}}`` for ``dotted`` = "section.key"."""
    section, _, name = dotted.rpartition(".")
    return {section: {name: value}} if section else {name: value}


def refused_at_load(dotted: str, value: Any) -> ConfigError:
    """The ConfigError of a configuration whose key ``dotted`` is ``value``."""
    with pytest.raises(ConfigError) as ei:
        DaemonConfig.from_dict(nested(dotted, value))
    return ei.value


#: The fakes' camera (H x W pixels).
CAM = Camera.d405(width=W, height=H, cx=W / 2, cy=H / 2)


class Published:
    """A viewer keeping each published frame's net force z (N) by frame index, in the order
    they were published."""

    def __init__(self) -> None:
        self.fz: dict[int, float] = {}

    def on_frame(self, frame: Any, msg: Any, mesh: Any, rec: Any) -> None:
        self.fz[int(frame.index)] = float(msg.net_force[2])

    def on_status(self, msg: Any, rec: Any) -> None:
        pass

    def close(self) -> None:
        pass


class FedCamera(IterableCamera):
    """Frames the test hands over one at a time (``feed``), so the daemon's stages can be
    stepped the same on any machine; ``close`` ends the stream."""

    def __init__(self) -> None:
        self._queue: queue.Queue[Frame | None] = queue.Queue()
        super().__init__(self._frames, CAM, rate_hz=None, loop=False)

    def _frames(self):  # type: ignore[no-untyped-def]
        while (f := self._queue.get(timeout=20.0)) is not None:
            yield f

    def feed(self, frame: Frame) -> None:
        self._queue.put(frame)

    def close(self) -> None:
        self._queue.put(None)


def start_fed(processor_factory: Any = None) -> tuple[Daemon, FedCamera]:
    """A daemon on a :class:`FedCamera` (a two-frame reference), started; nothing fed yet."""
    cam = FedCamera()
    d = Daemon(
        fake_config(**{"reference.frames": 2}),
        camera=cam,
        pressure=constant_pressure(),
        processor_factory=processor_factory or FakeProcessor,
    ).start()
    return d, cam


def feed_reference_and_first_frame(d: Daemon, cam: FedCamera) -> None:
    """Feed the two reference frames and frame A one by one; returns once A is published."""
    cam.feed(make_frame(0))
    assert wait_for(lambda: len(d.reference_collected) == 1)
    cam.feed(make_frame(1))
    assert wait_for(lambda: d.processor is not None)
    cam.feed(make_frame(2))
    assert wait_for(lambda: d.frames_published == 1)


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
    """:func:`start` with ``fake_config(**overrides)``, returning the daemon only."""
    return start(fake_config(**overrides), camera, pressure)[0]


def main() -> None:
    """Run a daemon on the fakes like `bubble-rt serve` does (signal handling included)."""
    import argparse

    from bubble_rt.commands.serve import install_signal_handlers, serve_until
    from bubble_rt.daemon.service import Daemon

    ap = argparse.ArgumentParser()
    ap.add_argument("--pub", required=True)
    ap.add_argument("--control", required=True)
    ap.add_argument("--record", default="")
    ap.add_argument("--sim", action="store_true", help="SimCamera on FakeSimulator")
    ap.add_argument("--duration", type=float, default=0.0)
    a = ap.parse_args()
    cfg = fake_config(
        **{"network.pub": a.pub, "network.control": a.control, "recording.path": a.record}
    )
    stop = threading.Event()
    install_signal_handlers(stop)
    camera: IterableCamera = ScriptedCamera()
    if a.sim:
        from bubble_rt.daemon.sim_camera import SimCamera

        camera = SimCamera("fake", simulator="daemon_fakes:FakeSimulator")
    d = Daemon(
        cfg, camera=camera, pressure=constant_pressure(), processor_factory=FakeProcessor
    ).start()
    serve_until(d, stop, a.duration)


if __name__ == "__main__":
    main()
