"""Start-up benchmark (not a test): how soon the first force frame reaches a subscriber.

Launches `bubble-rt serve` (sim camera by default) in a subprocess N times, subscribes to its
PUB address before it binds, and reports per run and as medians:

* launch -> first line: from ``Popen`` to the first line the daemon writes to stderr;
* first line -> first force frame: from that line to the first ForceFrame received;
* launch -> first force frame.

Times are the benchmark's wall clock (``time.monotonic``, seconds). Run it with a warm physics
cache (run once first) and say what else the machine was doing:

    OPENBLAS_NUM_THREADS=1 python3 bench/startup_bench.py --runs 5
    OPENBLAS_NUM_THREADS=1 python3 bench/startup_bench.py --runs 5 -- --mesh fine
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
from bubble_rt.io.client import Subscriber
from bubble_rt.io.protocol import ForceFrameData
from ports import local_addresses


def run_once(camera: str, extra: list[str], timeout_s: float) -> dict:
    """One launch: the three intervals (seconds; NaN when nothing arrived) and the log."""
    pub, ctl = local_addresses(2)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "bubble_rt", "serve", "--camera", camera]
    cmd += ["--pub", pub, "--control", ctl, *extra]
    lines: list[tuple[float, str]] = []
    first_line = threading.Event()
    with Subscriber(pub, ctl, timeout_s=timeout_s) as sub:
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)

        def read_stderr() -> None:
            assert proc.stderr is not None
            for line in proc.stderr:
                lines.append((time.monotonic() - t0, line.rstrip()))
                first_line.set()

        reader = threading.Thread(target=read_stderr, daemon=True)
        reader.start()
        t_frame = float("nan")
        try:
            end = t0 + timeout_s
            while time.monotonic() < end and proc.poll() is None:
                msg = sub.recv(0.05)
                if isinstance(msg, ForceFrameData):
                    t_frame = time.monotonic() - t0
                    break
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            reader.join(2)
    t_line = lines[0][0] if lines else float("nan")
    return {
        "launch_to_first_line_s": t_line,
        "first_line_to_first_frame_s": t_frame - t_line,
        "launch_to_first_frame_s": t_frame,
        "exit_code": proc.returncode,
        "log": [f"{t:6.2f} s  {text}" for t, text in lines],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="launches (medians over them)")
    ap.add_argument("--camera", default="sim", help="camera source (default: the demo scene)")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for a frame")
    ap.add_argument("--json", metavar="FILE", help="also write the runs and medians here")
    ap.add_argument("--log", action="store_true", help="print each run's stderr with times")
    ap.add_argument("serve_args", nargs="*", help="extra `bubble-rt serve` arguments after --")
    args = ap.parse_args()
    runs = []
    keys = ("launch_to_first_line_s", "first_line_to_first_frame_s", "launch_to_first_frame_s")
    for i in range(args.runs):
        r = run_once(args.camera, args.serve_args, args.timeout)
        runs.append(r)
        print(f"run {i + 1}: " + ", ".join(f"{k} {r[k]:.2f}" for k in keys), flush=True)
        if args.log:
            print("\n".join("    " + line for line in r["log"]), flush=True)
    med = {k: float(np.nanmedian([r[k] for r in runs])) for k in keys}
    load = os.getloadavg()
    print(
        f"median over {len(runs)} runs: launch -> first line {med[keys[0]]:.2f} s, "
        f"first line -> first force frame {med[keys[1]]:.2f} s, "
        f"launch -> first force frame {med[keys[2]]:.2f} s "
        f"(load average now {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f})",
        flush=True,
    )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"runs": runs, "median": med, "loadavg": load}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
