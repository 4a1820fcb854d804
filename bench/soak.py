"""Soak (not a test): the daemon for a long run on the demo scene under a control-request fuzzer.

Starts `bubble-rt serve` on the built-in simulated scene, subscribes to its force stream, and
runs a fuzzer that sends random, truncated, oversized, wrong-version and out-of-range control
requests (bounded in count and rate, loopback only). Every `--interval` seconds it samples the
daemon's resident memory, thread count, open file descriptors and the published frame rate.
It reports the start, end and maximum of each, the fuzzer's request/reply counts, and exits
non-zero if the daemon died or stopped publishing.

    OPENBLAS_NUM_THREADS=1 python3 bench/soak.py --minutes 30 --json soak.json
    python3 bench/soak.py --minutes 2 --interval 5        # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

import zmq
from bubble_rt.io import protocol
from bubble_rt.io.client import Controller, Subscriber
from bubble_rt.io.protocol import pb


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def proc_sample(pid: int) -> tuple[float, int, int]:
    """(RSS in MB, threads, open file descriptors) of process ``pid`` from /proc."""
    rss, threads = float("nan"), -1
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024.0
            elif line.startswith("Threads:"):
                threads = int(line.split()[1])
    return rss, threads, len(os.listdir(f"/proc/{pid}/fd"))


def fuzz_payload(rng: random.Random) -> bytes:
    """One hostile control request: valid, absurd, truncated, wrong-version or garbage."""
    kind = rng.randrange(7)
    req = pb.ControlRequest(protocol_version=protocol.PROTOCOL_VERSION)
    if kind == 0:
        req.get_status.SetInParent()
    elif kind == 1:
        # out-of-range and non-finite parameters: must be refused, never applied
        name = rng.choice(["k_f", "k_u", "youngs_modulus", "k_const", "k_linear"])
        value = rng.choice([0.0, -1.0, 5e-324, 1e308, float("nan"), float("inf"), 1.0])
        setattr(req.set_params, name, value)
    elif kind == 2:
        req.get_config.SetInParent()
    elif kind == 3:
        req.protocol_version = rng.choice([0, 2, 99, 2**32 - 1])
        req.get_mesh.SetInParent()
    elif kind == 4:
        req.get_mesh.SetInParent()
        raw = req.SerializeToString()
        return raw[: rng.randrange(max(len(raw), 1))]
    elif kind == 5:
        return rng.randbytes(rng.choice([1, 17, 300, 4096]))
    else:
        return rng.randbytes(rng.choice([1 << 20, 4 << 20]))
    return req.SerializeToString()


@dataclass
class FuzzStats:
    sent: int = 0
    replies: int = 0
    timeouts: int = 0
    errors: list[str] = field(default_factory=list)


def fuzz(ctl: str, stop: threading.Event, stats: FuzzStats, rate_hz: float, seed: int) -> None:
    rng = random.Random(seed)
    ctx = zmq.Context.instance()
    while not stop.is_set():
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.connect(ctl)
        try:
            s.send_multipart([b"", fuzz_payload(rng)])
            stats.sent += 1
            if s.poll(5000):
                s.recv_multipart()
                stats.replies += 1
            else:
                stats.timeouts += 1
        except zmq.ZMQError as exc:
            stats.errors.append(str(exc))
        finally:
            s.close()
        stop.wait(1.0 / rate_hz)


def count_frames(pub: str, ctl: str, stop: threading.Event, counter: list[int]) -> None:
    with Subscriber(pub, ctl, timeout_s=600) as sub:
        while not stop.is_set():
            msg = sub.recv(timeout_s=0.5)
            if msg is not None and hasattr(msg, "net_force"):
                counter[0] += 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--interval", type=float, default=10.0, help="seconds between samples")
    ap.add_argument("--fuzz-rate", type=float, default=50.0, help="control requests per second")
    ap.add_argument("--mesh", default="medium")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write every sample and the summary here")
    args = ap.parse_args()

    pub, ctl = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "bubble_rt", "serve", "--mesh", args.mesh]
    cmd += ["--pub", pub, "--control", ctl]
    log_path = f"/tmp/bubble_rt_soak_{os.getpid()}.log"
    log = open(log_path, "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, env=env, stderr=log, stdout=log)
    stop = threading.Event()
    frames = [0]
    stats = FuzzStats()
    samples: list[dict[str, float]] = []
    ok = True
    try:
        with Subscriber(pub, ctl, timeout_s=600) as sub:
            sub.fetch_mesh(600)  # waits out the first run's physics and the reference
        threads = [
            threading.Thread(target=count_frames, args=(pub, ctl, stop, frames), daemon=True),
            threading.Thread(
                target=fuzz, args=(ctl, stop, stats, args.fuzz_rate, args.seed), daemon=True
            ),
        ]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 120
        while frames[0] == 0 and time.monotonic() < deadline:
            time.sleep(0.1)  # the reference is captured before the first frame
        t0 = time.monotonic()
        last_n, last_t = frames[0], t0
        while time.monotonic() - t0 < args.minutes * 60:
            time.sleep(args.interval)
            if proc.poll() is not None:
                print(f"daemon exited with {proc.returncode}; log: {log_path}", flush=True)
                ok = False
                break
            rss, nthreads, fds = proc_sample(proc.pid)
            now = time.monotonic()
            rate = (frames[0] - last_n) / (now - last_t)
            last_n, last_t = frames[0], now
            row = {"t_s": round(now - t0, 1), "rss_mb": round(rss, 1), "threads": nthreads}
            row |= {"fds": fds, "rate_hz": round(rate, 2), "fuzz_sent": stats.sent}
            samples.append(row)
            print(json.dumps(row), flush=True)
            if rate == 0.0:
                ok = False
        with Controller(ctl, timeout_s=10) as c:
            status = c.status()
    finally:
        stop.set()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            ok = False
        log.close()
    if not samples:
        return 1
    summary: dict[str, object] = {"minutes": args.minutes, "mesh": args.mesh}
    for key in ("rss_mb", "threads", "fds", "rate_hz"):
        vals = [s[key] for s in samples]
        summary[key] = {"start": vals[0], "end": vals[-1], "max": max(vals), "min": min(vals)}
    summary["fuzz"] = {"sent": stats.sent, "replies": stats.replies, "timeouts": stats.timeouts}
    summary["daemon_exit_code"] = proc.returncode
    summary["final_state"] = status.state
    summary["frames_published"] = status.frames_published
    print(json.dumps(summary, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"summary": summary, "samples": samples}, f, indent=1)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
