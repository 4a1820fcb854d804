"""Soak (not a test): the daemon for a long run under a control-request fuzzer.

Starts `bubble-rt serve` on a simulated scene (default ``drift``: gas warming, a leak and LED
drift, an hour played per minute, looped, with re-zeroing on and scaled to the compression),
subscribes to its force stream, and runs two fuzzers: one sends random, truncated, oversized,
wrong-version and out-of-range control requests (bounded in count and rate, loopback only);
the other sends valid state-changing ones every few seconds (set_auto_zero, mostly on; tare;
a short record_start / record_stop into a temporary folder, deleted after). Every
`--interval` seconds it samples the daemon's resident memory, thread count, open file
descriptors, the published frame rate and the status's re-zero count and drift. It reports
the start, end, extremes and least-squares slope per 10 minutes (after `--warmup`) of each,
whether each is flat
(RSS within 10 MB, threads and fds within 0.5, rate within 5 % of its mean per 10 minutes),
the fuzzers' counts, and exits non-zero if the daemon died or stopped publishing.

    OPENBLAS_NUM_THREADS=1 nice -n 19 python3 bench/soak.py --minutes 30 --json soak.json
    python3 bench/soak.py --minutes 3 --interval 10       # a quick look
    python3 bench/soak.py --scene demo --no-auto-zero      # the former soak
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import zmq
from bubble_rt.io import protocol
from bubble_rt.io.client import Controller, Subscriber
from bubble_rt.io.protocol import pb
from ports import local_addresses


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


@dataclass
class ValidStats:
    sent: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)


def valid_ops(
    ctl: str, stop: threading.Event, stats: ValidStats, period_s: float, seed: int
) -> None:
    """Valid state changes every ``period_s``: set_auto_zero (on 3 times in 4), tare, or a
    recording of a second or two (deleted at once: the inputs are about 20 MB/s)."""
    rng = random.Random(seed + 1)
    folder = tempfile.mkdtemp(prefix="bubble_rt_soak_rec_")
    try:
        with Controller(ctl, timeout_s=10) as c:
            while not stop.wait(period_s):
                op = rng.choices(["auto_zero", "tare", "record"], weights=[6, 1, 2])[0]
                stats.sent[op] = stats.sent.get(op, 0) + 1
                try:
                    if op == "auto_zero":
                        c.set_auto_zero(rng.random() < 0.75)
                    elif op == "tare":
                        c.tare()
                    else:
                        path = c.record_start(os.path.join(folder, f"r{stats.sent[op]}.mcap"))
                        stop.wait(rng.uniform(0.5, 2.0))
                        c.record_stop()
                        if os.path.exists(path):
                            os.unlink(path)
                except Exception:
                    stats.refused[op] = stats.refused.get(op, 0) + 1
            c.set_auto_zero(True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def slope_per_10min(t_s: list[float], values: list[float]) -> float:
    """Least-squares slope of ``values`` over ``t_s`` (s), per 10 minutes."""
    if len(t_s) < 2:
        return 0.0
    t = [x - sum(t_s) / len(t_s) for x in t_s]
    v_mean = sum(values) / len(values)
    den = sum(x * x for x in t)
    return (
        600.0 * sum(x * (v - v_mean) for x, v in zip(t, values, strict=True)) / den if den else 0.0
    )


#: How much a quantity may move per 10 minutes and still count as flat.
FLAT_PER_10MIN = {"rss_mb": 10.0, "threads": 0.5, "fds": 0.5}
FLAT_RATE_FRACTION = 0.05


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
    ap.add_argument("--scene", default="drift", help="simulated scene (looped)")
    ap.add_argument("--no-auto-zero", action="store_true", help="re-zeroing off (and not fuzzed)")
    ap.add_argument(
        "--warmup", type=float, default=60.0, help="seconds left out of the slopes (start-up)"
    )
    ap.add_argument(
        "--valid-period", type=float, default=5.0, help="seconds between valid state changes"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write every sample and the summary here")
    args = ap.parse_args()

    pub, ctl = local_addresses(2)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    # The drift scene plays an hour per minute: re-zeroing scaled alike (60 s -> 1 s).
    cfg_path = f"/tmp/bubble_rt_soak_{os.getpid()}.toml"
    with open(cfg_path, "w") as f:
        f.write("[camera]\nsim_prerender = false\n[auto_zero]\n")
        f.write(f"enabled = {'false' if args.no_auto_zero else 'true'}\n")
        f.write("time_constant_s = 1.0\ninterval_s = 0.25\n")
    cmd = [sys.executable, "-m", "bubble_rt", "serve", "--mesh", args.mesh]
    cmd += ["--config", cfg_path, "--camera", f"sim:{args.scene}"]
    cmd += ["--pub", pub, "--control", ctl]
    log_path = f"/tmp/bubble_rt_soak_{os.getpid()}.log"
    log = open(log_path, "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, env=env, stderr=log, stdout=log)
    stop = threading.Event()
    frames = [0]
    stats = FuzzStats()
    vstats = ValidStats()
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
        if not args.no_auto_zero:
            threads.append(
                threading.Thread(
                    target=valid_ops,
                    args=(ctl, stop, vstats, args.valid_period, args.seed),
                    daemon=True,
                )
            )
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
            try:
                with Controller(ctl, timeout_s=5) as c:
                    st = c.status()
                row |= {"auto_zero": st.auto_zero, "rezero_count": st.rezero_count}
                row |= {"drift_pa": round(st.drift_pa, 1)}
            except Exception:
                row |= {"status": "no reply"}
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
    summary: dict[str, object] = {
        "minutes": args.minutes,
        "mesh": args.mesh,
        "scene": args.scene,
        "auto_zero": not args.no_auto_zero,
    }
    ts = [float(s["t_s"]) for s in samples]
    settled = [i for i, t in enumerate(ts) if t >= args.warmup] or list(range(len(ts)))
    summary["slopes_from_s"] = ts[settled[0]]
    for key in ("rss_mb", "threads", "fds", "rate_hz"):
        vals = [float(s[key]) for s in samples]
        tail = [vals[i] for i in settled]
        slope = slope_per_10min([ts[i] for i in settled], tail)
        limit = FLAT_PER_10MIN.get(key, FLAT_RATE_FRACTION * sum(tail) / len(tail))
        summary[key] = {
            "start": vals[0],
            "end": vals[-1],
            "max": max(vals),
            "min": min(vals),
            "slope_per_10min": round(slope, 3),
            "flat": abs(slope) <= limit,
        }
    summary["fuzz"] = {"sent": stats.sent, "replies": stats.replies, "timeouts": stats.timeouts}
    summary["valid_ops"] = {"sent": vstats.sent, "refused": vstats.refused}
    summary["rezero_count"] = samples[-1].get("rezero_count")
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
