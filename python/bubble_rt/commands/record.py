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
    from bubble_rt._validate import zmq_endpoint

    try:
        zmq_endpoint("--control", args.control)
    except ValueError as exc:
        print(f"bubble-rt record: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        return _record(args, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


#: While recording, the daemon is asked for its status this often; this many missed
#: replies in a row mean it is gone.
PROBE_S = 1.0
PROBE_MISSES = 3


def _record(args: argparse.Namespace, stop: threading.Event) -> int:
    from bubble_rt.io.client import ControlError, Controller

    path = str(Path(args.output).resolve())
    with Controller(args.control, timeout_s=5.0) as ctl:
        try:
            written = ctl.record_start(path, overwrite=getattr(args, "overwrite", False))
        except TimeoutError:
            print(
                f"bubble-rt record: no daemon answers at {args.control} (not running, or gone): "
                "nothing recorded",
                file=sys.stderr,
            )
            return 1
        except ControlError as exc:
            print(f"bubble-rt record: {exc}", file=sys.stderr)
            return 1
        print(f"recording to {written} (Ctrl-C to stop)", flush=True)
        end = time.monotonic() + args.duration if args.duration > 0 else None
        misses = 0
        next_probe = time.monotonic() + PROBE_S
        while not stop.wait(0.2) and (end is None or time.monotonic() < end):
            if time.monotonic() < next_probe:
                continue
            try:
                ctl.send_raw(_status_request(), timeout_s=PROBE_S)
                misses = 0
            except TimeoutError:
                misses += 1
                if misses >= PROBE_MISSES:
                    print(
                        f"bubble-rt record: the daemon at {args.control} is gone (no reply for "
                        f"{misses * PROBE_S:.0f} s); {_file_state(written)}",
                        file=sys.stderr,
                    )
                    return 1
            next_probe = time.monotonic() + PROBE_S
        try:
            done = ctl.record_stop()
        except TimeoutError:
            print(
                f"bubble-rt record: the daemon at {args.control} is gone (no reply to "
                f"record_stop); {_file_state(written)}",
                file=sys.stderr,
            )
            return 1
        except ControlError as exc:
            print(f"bubble-rt record: stopping failed: {exc}", file=sys.stderr)
            return 1
    print(f"wrote {done}")
    return 0


def _status_request() -> bytes:
    from bubble_rt.io import protocol

    return protocol.make_request("get_status").SerializeToString()


def _file_state(path: str) -> str:
    """What became of the recording the daemon was writing when it went away."""
    try:
        with open(path, "rb") as fh:
            fh.seek(-8, 2)
            closed = fh.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return f"{path} is not readable here (on another host?)"
    if closed:
        return f"{path} was finalised"
    return f"{path} was not finalised: `bubble-rt recover {path}` rewrites what it holds"
