"""Recording size and cost (not a test): MB per frame of `serve --record` on the demo scene for
each colour setting, what encoding costs per frame, and how far lossy colour moves the forces.

    OPENBLAS_NUM_THREADS=1 python3 bench/recording_size.py --seconds 60 --forces 90
    OPENBLAS_NUM_THREADS=1 python3 bench/recording_size.py --seconds 20 --settings png jpeg:75

Under load the sim renders slower than 30 Hz: MB per frame does not depend on the rate.

For each setting (``png``, ``jpeg:Q``, ``raw-lz4``: the layout before compression, colour as
RawImage in lz4 chunks, for comparison) it runs

    bubble-rt serve --duration S --record F --record-color C [--config recording.toml]

and reports the file size, the frames in it, MB per frame (file size over frames, reference frames included), the
messages the recorder dropped,
the daemon's published and dropped frames and latency p50 / p99 (from the recording's force
frames), and a 10-minute recording's size at the run's frame rate and at 30 Hz. Then, on the
frames of the png run, the per-frame encoding time of each codec (the recorder's thread does
it) and, with ``--forces``, the force difference of JPEG colour at quality Q: the lossless
recording and the same frames with JPEG colour, each replayed through the daemon (fast,
lossless, no solve time budget), |dF| of the net force per frame and the largest node |dF| (N).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def record(setting: str, seconds: float, out: Path) -> tuple[list[str], str]:
    """Run serve --record with one setting: (the command, its stderr)."""
    codec, _, q = setting.partition(":")
    toml = out.with_suffix(".toml")
    lines = ["[recording]"]
    if codec == "raw-lz4":
        lines.append('compression = "lz4"')
    elif q:
        lines.append(f"jpeg_quality = {int(q)}")
    toml.write_text("\n".join(lines) + "\n")
    cmd = [
        sys.executable,
        "-m",
        "bubble_rt",
        "serve",
        "--duration",
        str(seconds),
        "--record",
        str(out),
        "--pub",
        f"tcp://127.0.0.1:{free_port()}",
        "--control",
        f"tcp://127.0.0.1:{free_port()}",
        "--config",
        str(toml),
    ]
    if codec in ("png", "jpeg"):
        cmd += ["--record-color", codec]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    if codec == "raw-lz4":  # the writer as it was: colour as RawImage rgb8
        cmd[1:3] = ["-c", _RAW_SHIM]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=seconds + 300)
    return cmd, proc.stderr


# Runs the CLI with the colour written as RawImage rgb8 (the layout before this change).
_RAW_SHIM = (
    "import sys, bubble_rt.io.mcap as m; from bubble_rt.cli import main; "
    "m.color_image = lambda rgb, t, codec, q: m.raw_image(rgb, t); "
    "sys.argv = ['bubble-rt'] + sys.argv[1:]; sys.exit(main())"
)


def summarise(path: Path, stderr: str) -> dict:
    from bubble_rt.io.mcap import TOPIC_STATUS, McapRecording, iter_messages

    rec = McapRecording(path, warn=False)
    lat = [m.latency_ms for m in rec.force_frames()]
    dropped = 0
    for topic, msg, _, _ in iter_messages(path):
        if topic == TOPIC_STATUS:
            dropped = max(dropped, int(msg.recording_dropped))
    m = re.search(r"stopped after (\d+) frames \((\d+) dropped\)", stderr)
    published, daemon_dropped = (int(m.group(1)), int(m.group(2))) if m else (-1, -1)
    times = [f.t for f in rec]
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else float("nan")
    size = path.stat().st_size
    # Reference frames are frames too (colour, depth, pressure): the fixed part is the mesh,
    # camera info and settings (about 0.02 MB).
    n_ref = len(rec.reference_frames(1000))
    per = size / max(len(rec) + n_ref, 1) / 1e6
    return {
        "file_mb": size / 1e6,
        "frames": len(rec),
        "reference_frames": n_ref,
        "mb_per_frame": per,
        "recorder_dropped_messages": dropped,
        "published": published,
        "daemon_dropped": daemon_dropped,
        "latency_p50_ms": float(np.percentile(lat, 50)) if lat else float("nan"),
        "latency_p99_ms": float(np.percentile(lat, 99)) if lat else float("nan"),
        "frame_rate_hz": rate,
        "gb_10min_at_rate": per * rate * 600 / 1e3,
        "gb_10min_at_30hz": per * 30 * 600 / 1e3,
    }


def encode_costs(path: Path, n: int = 40) -> dict:
    """Median ms per frame of each encoding on the recording's frames (one thread)."""
    import zstandard
    from bubble_rt.io.image_codec import color_image, raw_image
    from bubble_rt.io.mcap import McapRecording

    frames = [f for _, f in zip(range(n), McapRecording(path, warn=False), strict=False)]
    out: dict[str, float] = {}

    def med(fn) -> float:  # type: ignore[no-untyped-def]
        ts = []
        for f in frames:
            t0 = time.perf_counter()
            fn(f)
            ts.append((time.perf_counter() - t0) * 1e3)
        return float(np.median(ts))

    out["jpeg90_ms"] = med(lambda f: color_image(f.rgb, f.t, "jpeg", 90))
    out["png_ms"] = med(lambda f: color_image(f.rgb, f.t, "png"))
    z = zstandard.ZstdCompressor()  # the mcap writer's default level
    out["depth_raw_zstd_ms"] = med(lambda f: z.compress(raw_image(f.depth, f.t).data))
    return out


def force_difference(png_path: Path, tmp: Path, quality: int) -> dict:
    """bubble-rt estimate on the lossless recording and on its frames with JPEG colour."""
    from bubble_rt.io import mcap as m
    from bubble_rt.io.mcap import McapRecording

    rec = McapRecording(png_path, warn=False)
    jpeg_path = tmp / f"jpeg{quality}.mcap"
    w = m.Recorder(jpeg_path, rec.camera, queue_size=1 << 30, jpeg_quality=quality)
    w.write_reference(rec.reference_frames(100))
    for f in rec:
        w.write_frame(f)
    assert w.close(timeout=600) and w.dropped == 0
    a, b = replay_forces(png_path, tmp / "a.mcap"), replay_forces(jpeg_path, tmp / "b.mcap")
    common = sorted(set(a) & set(b))
    d = np.array([np.linalg.norm(a[k].sum(axis=0) - b[k].sum(axis=0)) for k in common])
    node = np.array([np.abs(a[k] - b[k]).max() for k in common])
    mag = np.array([np.linalg.norm(a[k].sum(axis=0)) for k in common])
    return {
        "frames": len(common),
        "mean_abs_dF_N": float(d.mean()),
        "max_abs_dF_N": float(d.max()),
        "max_node_dF_N": float(node.max()),
        "mean_abs_F_N": float(mag.mean()),
        "max_abs_F_N": float(mag.max()),
    }


def replay_forces(path: Path, out: Path) -> dict[int, np.ndarray]:
    """Node forces (n x 3, N) per frame index of a fast, lossless replay of ``path`` through the
    daemon, with the configuration's settings and no solve time budget (deterministic)."""
    from bubble_rt.config import DaemonConfig
    from bubble_rt.daemon.service import Daemon
    from bubble_rt.io.mcap import McapRecording

    n = len(McapRecording(path, warn=False))
    cfg = DaemonConfig().with_overrides(
        **{
            "network.pub": f"tcp://127.0.0.1:{free_port()}",
            "network.control": f"tcp://127.0.0.1:{free_port()}",
            "camera.source": f"replay:{path}",
            "camera.pace": "fast",
            "camera.loop": False,
            "camera.replay_settings": "config",
            "solver.time_limit_ms": 0.0,
            "recording.path": str(out),
            "recording.queue": 100_000,
        }
    )
    d = Daemon(cfg).start()
    try:
        end = time.monotonic() + 1200
        while d.frames_published < n and time.monotonic() < end:
            time.sleep(0.1)
    finally:
        writer = d.recorder
        d.stop()
    writer.finished.wait(600)
    return {
        int(m.frame_index): np.asarray(m.node_forces).reshape(-1, 3)
        for m in McapRecording(out, warn=False).force_frames()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--settings", nargs="+", default=["jpeg:90", "png", "raw-lz4"])
    ap.add_argument("--forces", type=int, default=0, metavar="Q", help="JPEG quality to compare")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None, metavar="DIR", help="keep the recordings here")
    args = ap.parse_args()
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(args.keep or d)
        tmp.mkdir(parents=True, exist_ok=True)
        for s in args.settings:
            out = tmp / f"{s.replace(':', '_')}.mcap"
            cmd, err = record(s, args.seconds, out)
            if not out.exists():
                print(f"{s}: no recording\n{err}", file=sys.stderr)
                continue
            results[s] = summarise(out, err)
            print(s, json.dumps(results[s]), flush=True)
        png = tmp / "png.mcap"
        if png.exists():
            results["encode_ms"] = encode_costs(png)
            print("encode per frame", json.dumps(results["encode_ms"]), flush=True)
            if args.forces:
                results["force_difference"] = force_difference(png, tmp, args.forces)
                print("force difference", json.dumps(results["force_difference"]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
