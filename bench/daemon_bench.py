"""Daemon benchmark (not a test): sustained rate, latency percentiles and memory over time.

Runs `bubble-rt serve` in a subprocess for each mesh, subscribes with the client, and reports
the published frame rate, end-to-end latency (capture -> publish) p50 / p99, frames dropped and
the daemon's resident memory (VmRSS) after warm-up and at the end, and the time from SIGINT
to its exit.

    OPENBLAS_NUM_THREADS=1 python3 bench/daemon_bench.py --minutes 10
    python3 bench/daemon_bench.py --minutes 1 --meshes medium --camera sim
    python3 bench/daemon_bench.py --minutes 1 --meshes medium --foxglove   # with a viewer

Target (issue 5): keeps up with a 30 Hz camera at 640 x 480 on the 390-node mesh with p99
latency under 66 ms on a 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
from bubble_rt.io.client import Controller, Subscriber
from bubble_rt.io.protocol import MeshData
from ports import free_ports


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def mesh_while_running(sub: Subscriber, proc: subprocess.Popen, timeout_s: float) -> MeshData:
    """The daemon's mesh, asked for every few seconds while ``serve`` runs: a daemon that
    exits at start (a refused configuration) fails the run at once instead of after
    ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            return sub.fetch_mesh(5.0)
        except TimeoutError:
            if proc.poll() is not None:
                raise RuntimeError(f"serve exited with {proc.returncode} before its mesh") from None
            if time.monotonic() > end:
                raise


def run_one(
    mesh: str,
    minutes: float,
    camera: str,
    extra: list[str],
    warmup_s: float,
    foxglove: bool = False,
) -> dict:
    pub_port, ctl_port, fox_port = free_ports(3)
    pub, ctl = f"tcp://127.0.0.1:{pub_port}", f"tcp://127.0.0.1:{ctl_port}"
    fox = None
    if foxglove:  # serve --foxglove, with a client subscribed to every channel
        import threading

        from foxglove_client import connect

        fox_addr = f"ws://127.0.0.1:{fox_port}"
        extra = [*extra, "--foxglove", fox_addr]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [
        sys.executable,
        "-m",
        "bubble_rt",
        "serve",
        "--mesh",
        mesh,
        "--camera",
        camera,
        "--pub",
        pub,
        "--control",
        ctl,
        *extra,
    ]
    log = open(f"/tmp/daemon_bench_{mesh}_{os.getpid()}.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, env=env, stderr=log, text=True)
    lat: list[float] = []
    stages: dict[str, list[float]] = {}
    per_frame: list[tuple[float, dict[str, float], int]] = []
    #: Frames never published: gaps in frame_index, seen from outside (with the timings of the
    #: frames published either side of each gap).
    missing = 0
    gaps: list[dict] = []
    prev = None
    degraded = 0
    fox_stop = None
    try:
        with Subscriber(pub, ctl, timeout_s=600) as sub:
            mesh_data = mesh_while_running(sub, proc, 600)
            if foxglove:
                fox = connect(fox_addr)
                fox_stop = threading.Event()
                threading.Thread(target=fox.run, args=(fox_stop,), daemon=True).start()
            t_warm = time.monotonic() + warmup_s
            for _ in sub.frames(timeout_s=30):
                if time.monotonic() >= t_warm:
                    break
            rss_start = rss_mb(proc.pid)
            with Controller(ctl) as c:
                st0 = c.status()
            t0 = time.monotonic()
            fox_n0 = sum(fox.counts.values()) if fox else 0
            fox_b0 = fox.bytes if fox else 0
            end = t0 + minutes * 60
            n = 0
            for f in sub.frames(timeout_s=30):
                n += 1
                lat.append(f.latency_ms)
                if prev is not None and f.frame_index > prev.frame_index + 1:
                    missing += f.frame_index - prev.frame_index - 1
                    gaps.append(
                        {
                            "after_s": round(time.monotonic() - t0, 2),
                            "frames": f.frame_index - prev.frame_index - 1,
                            "first_missing_index": prev.frame_index + 1,
                            "before": {k: round(v, 1) for k, v in prev.timings_ms.items()},
                            "after": {k: round(v, 1) for k, v in f.timings_ms.items()},
                            "latency_before_after_ms": [
                                round(prev.latency_ms, 1),
                                round(f.latency_ms, 1),
                            ],
                        }
                    )
                prev = f
                degraded += f.degraded
                for k, v in f.timings_ms.items():
                    stages.setdefault(k, []).append(v)
                per_frame.append((f.latency_ms, dict(f.timings_ms), f.solver_iterations))
                if time.monotonic() >= end:
                    break
            elapsed = time.monotonic() - t0
            fox_msgs = (sum(fox.counts.values()) - fox_n0) if fox else 0
            fox_bytes = (fox.bytes - fox_b0) if fox else 0
            rss_end = rss_mb(proc.pid)
            with Controller(ctl) as c:
                st1 = c.status()
    finally:
        if fox_stop is not None and fox is not None:
            fox_stop.set()
            fox.close()
        t_signal = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
            shutdown_s = time.monotonic() - t_signal  # docs/daemon.md: within 2 s
        except subprocess.TimeoutExpired:
            proc.kill()
            shutdown_s = float("nan")
        log.close()
    a = np.asarray(lat)
    # What the slowest 1 % of frames (latency >= p99) spent their time on, against the median.
    cut = float(np.percentile(a, 99))
    tail = [(t, it) for lat_ms, t, it in per_frame if lat_ms >= cut]
    tail_stages = {
        k: round(float(np.median([t.get(k, 0.0) for t, _ in tail])), 2) for k in sorted(stages)
    }
    return {
        "mesh": mesh,
        "nodes": mesh_data.n_nodes,
        "camera": camera,
        "seconds": round(elapsed, 1),
        "frames": n,
        "rate_hz": round(n / elapsed, 2),
        "dropped": st1.frames_dropped - st0.frames_dropped,
        "missing": missing,
        "gaps": gaps[:20],
        "missing_indices": [g["first_missing_index"] for g in gaps],
        "load": os.getloadavg()[0],
        "degraded_frames": degraded,
        "latency_p50_ms": round(float(np.percentile(a, 50)), 1),
        "latency_p99_ms": round(float(np.percentile(a, 99)), 1),
        "latency_max_ms": round(float(a.max()), 1),
        "stage_p50_ms": {k: round(float(np.median(v)), 2) for k, v in sorted(stages.items())},
        "tail_frames": len(tail),
        "tail_stage_p50_ms": tail_stages,
        "tail_iterations": sorted(int(it) for _, it in tail),
        "iterations_p50": float(np.median([it for _, _, it in per_frame])),
        "rss_start_mb": round(rss_start, 1),
        "rss_end_mb": round(rss_end, 1),
        "shutdown_s": round(shutdown_s, 2),
        "foxglove_msgs_per_s": round(fox_msgs / elapsed, 1) if foxglove else None,
        "foxglove_mb_per_s": round(fox_bytes / elapsed / 1e6, 2) if foxglove else None,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="measurement time per mesh")
    ap.add_argument("--meshes", default="coarse,medium,fine")
    ap.add_argument("--camera", default="sim", help="camera source (default: the demo scene)")
    ap.add_argument("--warmup", type=float, default=10.0, help="seconds ignored at the start")
    ap.add_argument("--json", action="store_true")
    ap.add_argument(
        "--foxglove", action="store_true", help="serve --foxglove with a subscribed client"
    )
    ap.add_argument("serve_args", nargs="*", help="extra `bubble-rt serve` arguments after --")
    args = ap.parse_args()
    rows = []
    for mesh in args.meshes.split(","):
        r = run_one(mesh, args.minutes, args.camera, args.serve_args, args.warmup, args.foxglove)
        rows.append(r)
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print(
                f"{r['mesh']:>7} ({r['nodes']} nodes): {r['rate_hz']:5.1f} Hz over {r['seconds']} s,"
                f" latency p50 {r['latency_p50_ms']} ms p99 {r['latency_p99_ms']} ms"
                f" (max {r['latency_max_ms']}), dropped {r['dropped']} (frame_index gaps"
                f" {r['missing']}), degraded"
                f" {r['degraded_frames']}, RSS {r['rss_start_mb']} -> {r['rss_end_mb']} MB,"
                f" SIGINT to exit {r['shutdown_s']} s",
                flush=True,
            )
            print(f"         stage medians (ms): {r['stage_p50_ms']}", flush=True)
            print(
                f"         the {r['tail_frames']} frames at or over p99: stage medians (ms)"
                f" {r['tail_stage_p50_ms']}, solver iterations {r['tail_iterations']}"
                f" (all frames' median {r['iterations_p50']:g})",
                flush=True,
            )
            print(f"         load average (1 min) at the end: {r['load']:.2f}", flush=True)
            if r["missing_indices"]:
                print(
                    f"         first missing frame_index of each gap: {r['missing_indices'][:60]}"
                )
            for g in r["gaps"]:
                print(f"         gap: {g}", flush=True)
            if args.foxglove:
                print(
                    f"         foxglove client: {r['foxglove_msgs_per_s']} msg/s,"
                    f" {r['foxglove_mb_per_s']} MB/s",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
