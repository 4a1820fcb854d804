"""Recording size and cost (not a test): MB per frame of `serve --record` on the demo scene for
each colour setting, what encoding costs per frame, and how far lossy colour moves the forces.

    OPENBLAS_NUM_THREADS=1 python3 bench/recording_size.py --seconds 60 --forces 90 \
        --real ../shared/data/punyo-demo-0-press
    OPENBLAS_NUM_THREADS=1 python3 bench/recording_size.py --seconds 20 --settings png jpeg:75

Under load the sim renders slower than 30 Hz: MB per frame does not depend on the rate.

For each setting (``png``, ``jpeg:Q``, ``raw-lz4``: the layout before compression, colour as
RawImage in lz4 chunks, for comparison) it runs

    bubble-rt serve --duration S --record F --record-color C [--config recording.toml]

and reports the file size, the frames in it, MB per frame (file size over the frames whose
images are in it, reference frames included), the messages the recorder dropped, the daemon's published and dropped frames
and latency p50 / p99 (from the recording's force frames), and a 10-minute recording's size
at the run's frame rate and at 30 Hz. Then, on 40 frames of the png run (and with ``--real
DIR`` on a real recording's frames), the per-frame CPU time and size of each encoding on one
thread (the recorder's thread does it in the daemon), with the 16-bit PNG depth measured
against the zstd chunks; and, with ``--forces Q``, the force difference of JPEG colour at
quality Q: the lossless recording and the same frames with JPEG colour, each replayed through
the daemon (fast, lossless, no solve time budget), |dF| of the net force and of the node
forces per frame (N).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from ports import local_addresses


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
    pub, ctl = local_addresses(2)
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
        pub,
        "--control",
        ctl,
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
    "import sys, bubble_rt.io.mcap_writer as m; from bubble_rt.cli import main; "
    "m.color_image = lambda rgb, t, codec, q: m.raw_image(rgb, t); "
    "sys.argv = ['bubble-rt'] + sys.argv[1:]; sys.exit(main())"
)


def summarise(path: Path, stderr: str) -> dict:
    from collections import Counter

    from bubble_rt.io import mcap as m

    rec = m.McapRecording(path, warn=False)
    lat = [f.latency_ms for f in rec.force_frames()]
    dropped = 0
    count: Counter[str] = Counter()
    for topic, msg, _, _ in m.iter_messages(path):
        count[topic] += 1
        if topic == m.TOPIC_STATUS:
            dropped = max(dropped, int(msg.recording_dropped))
    # Frames whose images are in the file (a recorder that falls behind drops some messages of
    # a frame, the pressure included): reference frames count, they are frames too.
    images = max(
        count[m.TOPIC_RGB] + count[m.TOPIC_REF_RGB], count[m.TOPIC_DEPTH] + count[m.TOPIC_REF_DEPTH]
    )
    m = re.search(r"stopped after (\d+) frames \((\d+) dropped\)", stderr)
    published, daemon_dropped = (int(m.group(1)), int(m.group(2))) if m else (-1, -1)
    times = [f.t for f in rec]
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else float("nan")
    size = path.stat().st_size
    n_ref = len(rec.reference_frames(1000))
    per = size / max(images, 1) / 1e6  # the fixed part (mesh, settings) is about 0.02 MB
    return {
        "file_mb": size / 1e6,
        "frames": len(rec),
        "reference_frames": n_ref,
        "frames_with_images": images,
        "closed": rec.report.closed,
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


def encode_costs(frames: list, step_m: float = 1e-4) -> dict:
    """Median CPU ms per frame (process time: what the encoder costs, not how long a loaded
    machine made it wait) and mean MB per frame of each encoding of ``frames`` (one thread),
    and the 16-bit PNG of the depth that was measured against the zstd chunks: lossless only
    where every depth lies on the sensor's ``step_m`` grid (``depth_on_grid``: the share of
    pixels that do, 1.0 for lossless)."""
    import cv2
    import zstandard
    from bubble_rt.io.image_codec import color_image, raw_image

    z = zstandard.ZstdCompressor()  # the mcap writer's zstd (default level)
    step = np.float32(step_m)
    on_grid = [
        float(np.mean((np.round(f.depth / step).astype(np.float32) * step) == f.depth))
        for f in frames
    ]
    codecs = {
        "colour_jpeg90": lambda f: color_image(f.rgb, f.t, "jpeg", 90).data,
        "colour_png": lambda f: color_image(f.rgb, f.t, "png").data,
        "colour_raw_zstd": lambda f: z.compress(raw_image(f.rgb, f.t).data),
        "depth_raw_zstd": lambda f: z.compress(raw_image(f.depth, f.t).data),
        "depth_png16": lambda f: cv2.imencode(
            ".png", np.round(f.depth / step).astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1]
        )[1],
    }
    out: dict[str, float] = {"frames": len(frames), "depth_on_grid": float(np.min(on_grid))}
    for name, fn in codecs.items():
        ts, sizes = [], []
        for f in frames:
            t0 = time.process_time()
            sizes.append(len(fn(f)))
            ts.append((time.process_time() - t0) * 1e3)
        out[f"{name}_ms"] = float(np.median(ts))
        out[f"{name}_mb"] = float(np.mean(sizes)) / 1e6
    return out


def force_difference(png_path: Path, tmp: Path, quality: int) -> dict:
    """bubble-rt estimate on the lossless recording and on its frames with JPEG colour."""
    from bubble_rt.io.mcap import McapRecording
    from bubble_rt.io.mcap_writer import Recorder

    rec = McapRecording(png_path, warn=False)
    jpeg_path = tmp / f"jpeg{quality}.mcap"
    w = Recorder(jpeg_path, rec.camera, queue_size=1 << 30, jpeg_quality=quality)
    w.write_reference(rec.reference_frames(100))
    for f in rec:
        w.write_frame(f)
    assert w.close(timeout=600) and w.dropped == 0
    return compare_forces(
        replay_forces(png_path, tmp / "a.mcap"), replay_forces(jpeg_path, tmp / "b.mcap")
    )


def compare_forces(a: dict[int, Any], b: dict[int, Any]) -> dict:
    """|dF| between two runs' ForceFrames (by frame index): net, node and patch forces (N)."""
    common = sorted(set(a) & set(b))

    def nodes(msg) -> np.ndarray:  # type: ignore[no-untyped-def]
        return np.asarray(msg.node_forces).reshape(-1, 3)

    def patch_forces(msg) -> list[float]:  # type: ignore[no-untyped-def]
        return sorted(float(np.linalg.norm(p.force)) for p in msg.patches)

    net = np.array([np.linalg.norm(np.subtract(a[k].net_force, b[k].net_force)) for k in common])
    node = [np.linalg.norm(nodes(a[k]) - nodes(b[k]), axis=1) for k in common]
    per_max = np.array([n.max() for n in node])
    per_mean = np.array([n.mean() for n in node])
    patches = [(patch_forces(a[k]), patch_forces(b[k])) for k in common]
    same_count = [(pa, pb) for pa, pb in patches if len(pa) == len(pb)]
    patch_d = [
        max((abs(x - y) for x, y in zip(pa, pb, strict=True)), default=0.0) for pa, pb in same_count
    ]
    return {
        "frames": len(common),
        "net_dF_mean_N": float(net.mean()),
        "net_dF_max_N": float(net.max()),
        "node_dF_per_frame_mean_N": {"mean": float(per_mean.mean()), "max": float(per_mean.max())},
        "node_dF_per_frame_max_N": {
            "median": float(np.median(per_max)),
            "p90": float(np.percentile(per_max, 90)),
            "max": float(per_max.max()),
        },
        "node_f_max_N": float(max(np.linalg.norm(nodes(a[k]), axis=1).max() for k in common)),
        "patch_dF_max_N": float(max(patch_d, default=0.0)),
        "frames_patch_count_differs": len(patches) - len(same_count),
        "frames_contact_differs": sum(a[k].contact != b[k].contact for k in common),
        "net_F_mean_N": float(np.mean([np.linalg.norm(a[k].net_force) for k in common])),
        "net_F_max_N": float(max(np.linalg.norm(a[k].net_force) for k in common)),
    }


def replay_forces(path: Path, out: Path) -> dict[int, Any]:
    """The ForceFrame per frame index of a fast, lossless replay of ``path`` through the
    daemon, with the configuration's settings and no solve time budget (deterministic)."""
    from bubble_rt.config import DaemonConfig
    from bubble_rt.daemon.service import Daemon
    from bubble_rt.io.mcap import McapRecording

    n = len(McapRecording(path, warn=False))
    pub, ctl = local_addresses(2)
    cfg = DaemonConfig().with_overrides(
        **{
            "network.pub": pub,
            "network.control": ctl,
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
    return {int(f.frame_index): f for f in McapRecording(out, warn=False).force_frames()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--settings", nargs="+", default=["jpeg:90", "png", "raw-lz4"])
    ap.add_argument("--forces", type=int, default=0, metavar="Q", help="JPEG quality to compare")
    ap.add_argument("--json", default=None)
    ap.add_argument("--real", default=None, metavar="DIR", help="also encode a real recording")
    ap.add_argument("--keep", default=None, metavar="DIR", help="keep the recordings here")
    args = ap.parse_args()
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(args.keep or d)
        tmp.mkdir(parents=True, exist_ok=True)
        for i, s in enumerate(args.settings):  # a setting may repeat (runs alternated)
            name = s.replace(":", "_")
            out = tmp / (f"{name}.mcap" if s not in args.settings[:i] else f"{name}-{i}.mcap")
            cmd, err = record(s, args.seconds, out)
            if not out.exists():
                print(f"{s}: no recording\n{err}", file=sys.stderr)
                continue
            results[out.stem] = summarise(out, err)
            print(s, json.dumps(results[out.stem]), flush=True)
        png = tmp / "png.mcap"
        if png.exists():
            from bubble_rt.io.mcap import McapRecording

            sim = [f for _, f in zip(range(40), McapRecording(png, warn=False), strict=False)]
            results["encode_demo"] = encode_costs(sim)
            print("encoding, demo frames", json.dumps(results["encode_demo"]), flush=True)
            if args.forces:
                results["force_difference"] = force_difference(png, tmp, args.forces)
                print("force difference", json.dumps(results["force_difference"]), flush=True)
    if args.real:
        from bubble_rt.io.recordings import open_recording

        results["encode_real"] = encode_costs(list(open_recording(args.real)))
        print("encoding, real frames", json.dumps(results["encode_real"]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
