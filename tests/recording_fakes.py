"""Small recordings for the reader and replay tests: a Punyo folder, PNG-folder frames, a
recording cut by a crash (ROS 2 bags: ``broken_bags``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.io.image_codec import raw_image
from bubble_rt.io.mcap import (
    TOPIC_DEPTH,
    TOPIC_PRESSURE,
    TOPIC_RGB,
    iter_messages,
)
from bubble_rt.io.mcap_writer import Recorder
from bubble_rt.io.protocol import pb
from daemon_fakes import CAM, P0, make_frame

H, W = 24, 32
FX, FY, CX, CY = 40.0, 41.0, 15.2, 11.7


def plane_cloud(z0: float) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = z0 + 0.0005 * u
    return np.dstack([(u - CX) / FX * z, (v - CY) / FY * z, z]).reshape(-1, 3).astype(np.float32)


def make_punyo(root: Path, n: int = 3, with_json: bool = True) -> None:
    exp = root / "expand"
    exp.mkdir(parents=True)
    rows = []
    for i in range(n):
        rgb = np.zeros((H, W, 3), np.uint8)
        rgb[..., 0] = 10 * i
        rgb[..., 1] = 200
        pc = plane_cloud(0.08 + 0.001 * i)
        pc[:5] = 0.0  # no reading
        pc[7, 2] = 6.5535  # saturated
        np.save(exp / f"rgb_{i}.npy", rgb)
        np.save(exp / f"pc_{i}.npy", pc)
        np.save(exp / f"pressure_{i}.npy", np.float64(1065.0 + i))
        rows.append([1000.0 + i / 30, 1065.0 + i, [0.1] * 6, [0.5, -0.2, 1.0 + i, 0, 0, 0.01]])
    if with_json:
        (root / "data.json").write_text(json.dumps(rows))


def png_frames(n: int, wrench: bool) -> tuple[list[Frame], Camera]:
    cam = Camera(fx=FX, fy=FY, cx=CX, cy=CY, width=W, height=H)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        depth = np.full((H, W), 0.0812 + 0.001 * i, np.float32)
        depth[0, :4] = 0.0
        w = np.array([0.1 * i, 0, -1.0, 0, 0, 0]) if wrench else None
        frames.append(Frame(rgb, depth, 106500.0 + i, t=0.5 * i, wrench=w, index=i))
    return frames, cam


def killed_recording(path: Path, frames: int = 12, more: int = 0) -> Path:
    """An MCAP recording cut by a crash: a subprocess records ``frames`` frames
    (``daemon_fakes.make_frame``), waits until they are flushed to ``path``, queues ``more``,
    and is killed (SIGKILL) with no summary or footer written."""
    import signal
    import subprocess
    import sys

    script = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from recording_fakes import _record_until_killed\n"
        f"_record_until_killed({str(path)!r}, {frames}, {more})\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "flushed"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    return path


def _record_until_killed(path: str, frames: int, more: int) -> None:
    """:func:`killed_recording`'s child process."""

    from bubble_rt.io.mcap import iter_messages

    def on_disk() -> int:  # messages readable in the file (a chunk is there once flushed)
        try:
            return sum(1 for _ in iter_messages(path))
        except Exception:  # nothing flushed yet: not an MCAP file so far
            return 0

    rec = Recorder(path, Camera.d405(), chunk_size=1 << 30, flush_s=0.05)
    for i in range(frames):
        rec.write_frame(make_frame(i))
    while on_disk() < 1 + 3 * frames:  # camera info, then RGB, depth and pressure per frame
        time.sleep(0.01)
    print("flushed", flush=True)
    for i in range(frames, frames + more):
        rec.write_frame(make_frame(i))
    time.sleep(600)  # killed meanwhile: a crash, not an exit


def log_times(path):  # type: ignore[no-untyped-def]
    return [t for _, _, t, _ in iter_messages(path)]


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
