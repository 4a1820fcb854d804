"""`bubble-rt record -o FILE`: make a running daemon record its inputs and outputs (MCAP)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

HELP = "record a running daemon's inputs and force frames to an MCAP file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write")
    parser.add_argument("--control", default="tcp://127.0.0.1:5556", help="daemon control address")
    parser.add_argument(
        "--duration", type=float, default=0.0, help="seconds to record (0: until Ctrl-C)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file")


def run(args: argparse.Namespace) -> int:
    stop = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        return _record(args, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _record(args: argparse.Namespace, stop: threading.Event) -> int:
    from bubble_rt.io.client import ControlError, Controller

    path = str(Path(args.output).resolve())
    with Controller(args.control, timeout_s=5.0) as ctl:
        try:
            written = ctl.record_start(path, overwrite=getattr(args, "overwrite", False))
        except (ControlError, TimeoutError) as exc:
            print(f"bubble-rt record: {exc}", file=sys.stderr)
            return 1
        print(f"recording to {written} (Ctrl-C to stop)", flush=True)
        end = time.monotonic() + args.duration if args.duration > 0 else None
        while not stop.wait(0.2) and (end is None or time.monotonic() < end):
            pass
        try:
            done = ctl.record_stop()
        except (ControlError, TimeoutError) as exc:
            print(f"bubble-rt record: stopping failed: {exc}", file=sys.stderr)
            return 1
    print(f"wrote {done}")
    return 0
