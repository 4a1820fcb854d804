"""Device sources: an Intel RealSense camera (pyrealsense2) and a serial pressure sensor
(pyserial), each on its own thread like every source (:mod:`bubble_rt.daemon.sources`). The
devices are optional imports: without one, the source says what to install or connect."""

from __future__ import annotations

import logging
import math
import re
import time
from typing import Any

import numpy as np

from bubble_rt.camera import Camera
from bubble_rt.daemon.sources import (
    HPA,
    CameraSource,
    PressureBuffer,
    SourceError,
    ThreadedSource,
)
from bubble_rt.frames import Frame

log = logging.getLogger("bubble_rt.daemon.sources")


class RealSenseCamera(CameraSource):
    """Intel RealSense (D405) through pyrealsense2: colour + depth aligned to colour.

    Stalls (no frame within ``timeout_ms``) are counted; after ``max_stalls`` in a row the
    pipeline is restarted (unplug / replug recovers by itself).
    """

    name = "realsense"
    layout = "realsense"  # Punyo hardware: bubble_rt.sensor picks the Punyo profile
    retry_s = 1.0

    def __init__(
        self,
        serial: str = "",
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        timeout_ms: int = 1000,
        max_stalls: int = 3,
        rs_module: Any = None,
    ) -> None:
        super().__init__()
        self.serial = serial
        self.width, self.height, self.fps = width, height, fps
        self.timeout_ms = timeout_ms
        self.max_stalls = max_stalls
        self._rs = rs_module
        self._pipe: Any = None
        self._depth_scale = 0.0

    def _module(self) -> Any:
        if self._rs is None:
            try:
                import pyrealsense2 as rs
            except ImportError:
                raise SourceError(
                    "camera source 'realsense' needs pyrealsense2, which is not installed: "
                    "pip install 'bubble_rt[realsense]' (or pip install pyrealsense2)"
                ) from None
            self._rs = rs
        return self._rs

    def _open(self) -> None:
        rs = self._module()
        devices = list(rs.context().query_devices())
        if not devices:
            raise SourceError(
                "no RealSense device found: check the USB 3 cable and that no other program "
                "holds the camera (realsense-viewer)"
            )
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, self.fps)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipe = rs.pipeline()
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise SourceError(f"cannot start the RealSense streams: {exc}") from exc
        self._depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        coeffs = tuple(float(c) for c in list(intr.coeffs)[:5])
        self.camera = Camera(
            fx=float(intr.fx),
            fy=float(intr.fy),
            cx=float(intr.ppx),
            cy=float(intr.ppy),
            width=int(intr.width),
            height=int(intr.height),
            distortion=coeffs + (0.0,) * (5 - len(coeffs)),  # type: ignore[arg-type]
        )
        self._align = rs.align(rs.stream.color)
        self._pipe = pipe

    def _close(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except Exception:
                pass
            self._pipe = None

    def prepare(self) -> None:
        self._open()

    def _run(self) -> bool | None:
        if self._pipe is None:
            self._open()
        stalls = 0
        try:
            while not self._stop.is_set():
                try:
                    frames = self._pipe.wait_for_frames(self.timeout_ms)
                except RuntimeError as exc:
                    stalls += 1
                    self.stats.error("stall", f"no frame within {self.timeout_ms} ms: {exc}")
                    if stalls >= self.max_stalls:
                        raise SourceError(f"camera lost after {stalls} stalls") from exc
                    continue
                stalls = 0
                t = time.time()
                aligned = self._align.process(frames)
                color = aligned.get_color_frame()
                depth = aligned.get_depth_frame()
                if not color or not depth:
                    self.stats.error("incomplete", "frame set without colour or depth")
                    continue
                rgb = np.array(np.asanyarray(color.get_data()), dtype=np.uint8, copy=True)
                z = np.asanyarray(depth.get_data()).astype(np.float32) * self._depth_scale
                idx = self._count
                self._count += 1
                try:
                    # The camera has no pressure: the daemon pairs one from the pressure source.
                    frame = Frame(
                        rgb=rgb,
                        depth=z,
                        pressure_pa=0.0,
                        t=t,
                        index=idx,
                        meta={
                            "device_time_ms": float(frames.get_timestamp()),
                            "has_pressure": False,
                        },
                    )
                except ValueError as exc:  # e.g. no valid depth pixel (lens covered)
                    self.stats.error("bad_frame", str(exc))
                    continue
                self.emit(frame)
        finally:
            self._close()
        return None

    def stop(self, timeout: float = 1.0) -> None:
        super().stop(timeout)
        self._close()


# ------------------------------------------------------------------------------ serial
_LINE = re.compile(
    r"^\s*(?P<value>[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*(?P<unit>hPa|Pa|mbar)?"
    r"(\s+t\s*=\s*(?P<t>[-+]?\d+(\.\d*)?))?\s*$"
)


class LineError(ValueError):
    """A serial line that is not a valid reading; ``kind`` classifies it for the counters."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind


def parse_pressure_line(
    raw: bytes, default_unit: str = "hPa", min_pa: float = 30000.0, max_pa: float = 200000.0
) -> tuple[float, float | None] | None:
    """Parse one line of the serial protocol: ``<value> [hPa|Pa|mbar] [t=<sensor ms>]``.

    Returns (pascals, sensor time ms or None), or None for a blank line or a ``#`` comment.
    Raises :class:`LineError` with kind "garbage" (not text), "non_numeric" or "out_of_range".
    """
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise LineError("garbage", f"not ASCII text: {raw[:32]!r}") from None
    if not text or text.startswith("#"):
        return None
    if any(not c.isprintable() for c in text):
        raise LineError("garbage", f"control characters in line: {text[:32]!r}")
    m = _LINE.match(text)
    if m is None:
        raise LineError("non_numeric", f"not a reading: {text[:40]!r}")
    value = float(m.group("value"))
    unit = m.group("unit") or default_unit
    pa = value if unit == "Pa" else value * HPA
    if not (math.isfinite(pa) and min_pa <= pa <= max_pa):
        raise LineError("out_of_range", f"{pa:.0f} Pa outside [{min_pa:.0f}, {max_pa:.0f}] Pa")
    t = m.group("t")
    return pa, (float(t) if t is not None else None)


class SerialPressure(ThreadedSource):
    """Pressure readings from a serial port (pyserial), one per line, into ``buffer``.

    Faults are counted in ``stats.errors`` by kind: garbage, non_numeric, out_of_range,
    partial (a line cut at (re)connection or longer than ``max_line`` bytes) and port
    (the port vanished; it is reopened every ``reconnect_s``).
    """

    name = "serial"
    max_line = 128

    def __init__(
        self,
        port: str,
        buffer: PressureBuffer,
        baud: int = 115200,
        default_unit: str = "hPa",
        min_pa: float = 30000.0,
        max_pa: float = 200000.0,
        reconnect_s: float = 0.5,
    ) -> None:
        super().__init__()
        self.port = port
        self.buffer = buffer
        self.baud = baud
        self.default_unit = default_unit
        self.min_pa, self.max_pa = min_pa, max_pa
        self.retry_s = reconnect_s
        self.name = f"serial:{port}"
        self.stats.name = self.name
        self.last_sensor_ms: float | None = None

    def _main(self) -> None:
        while not self._stop.is_set():
            try:
                self._run()
            except Exception as exc:
                self.stats.connected = False
                self.stats.error("port", f"serial port {self.port}: {type(exc).__name__}: {exc}")
                self._stop.wait(self.retry_s)

    def _run(self) -> bool | None:
        import serial

        with serial.serial_for_url(self.port, baudrate=self.baud, timeout=0.05) as ser:
            self.stats.connected = True
            pending = b""
            # The first line after opening is usually cut: we joined the stream mid-line.
            first = True
            while not self._stop.is_set():
                chunk = ser.read(ser.in_waiting or 1)
                if not chunk:
                    continue
                pending += chunk
                *lines, pending = pending.split(b"\n")
                for line in lines:
                    if first:
                        first = False
                        if line.strip():
                            self.stats.error("partial", f"discarded first line {line[:32]!r}")
                        continue
                    if len(line) > self.max_line:
                        self.stats.error("partial", f"line longer than {self.max_line} bytes")
                        continue
                    self._handle(line)
                if len(pending) > self.max_line:
                    self.stats.error("partial", f"line longer than {self.max_line} bytes")
                    pending = b""
                    first = True  # resynchronise at the next newline
        return None

    def _handle(self, line: bytes) -> None:
        try:
            got = parse_pressure_line(line, self.default_unit, self.min_pa, self.max_pa)
        except LineError as exc:
            self.stats.error(exc.kind, str(exc))
            return
        if got is None:
            return
        pa, sensor_ms = got
        now = time.time()
        self.last_sensor_ms = sensor_ms
        self.stats.received += 1
        self.stats.last_time = now
        self.buffer.push(now, pa)


# ------------------------------------------------------------------------------ factory
