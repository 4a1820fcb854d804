"""`bubble-rt echo`: one line per force frame received from a running daemon."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

HELP = "print a live one-line summary per force frame published by a daemon"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "address", nargs="?", default="tcp://127.0.0.1:5555", help="daemon PUB address"
    )
    parser.add_argument("--sensor", default="", help="only this sensor id (default: all)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--count", type=int, default=0, help="stop after N frames (0: never)")
    parser.add_argument(
        "--timeout", type=float, default=0.0, help="give up after S seconds without a frame"
    )


class RateMeter:
    """Frames per second over a sliding window of publish times (ns)."""

    def __init__(self, window: int = 30) -> None:
        self.times: list[int] = []
        self.window = window

    def add(self, t_ns: int) -> float:
        self.times.append(t_ns)
        self.times = self.times[-self.window :]
        if len(self.times) < 2 or self.times[-1] <= self.times[0]:
            return 0.0
        return (len(self.times) - 1) / ((self.times[-1] - self.times[0]) / 1e9)


def _vec(f: Any) -> tuple[float, float, float, float]:
    fx, fy, fz = (float(f[0]), float(f[1]), float(f[2])) if len(f) == 3 else (0.0, 0.0, 0.0)
    return fx, fy, fz, (fx * fx + fy * fy + fz * fz) ** 0.5


def format_line(frame: Any, rate_hz: float, state: str) -> str:
    """``seq  rate  latency  net force  |F|  net torque  contact nodes/patches  state`` (N,
    mN m about the mesh origin, ms, Hz); the torque is left out for a frame without one.

    A frame with simulation truth (``has_truth``: simulated sources only) gets the truth
    beside the estimate: ``| true F [..] N |F| .. N contact .. nodes IoU ..`` (IoU of the
    estimated contact nodes against the true ones, "-" when neither has any).
    """
    fx, fy, fz, mag = _vec(frame.net_force)
    tau = getattr(frame, "net_torque", None)
    torque = ""
    if tau is not None:
        mx, my, mz, _ = _vec(1e3 * tau)
        torque = f"tau [{mx:+6.1f} {my:+6.1f} {mz:+6.1f}] mNm  "
    flag = " DEGRADED: " + "; ".join(frame.degraded_reasons) if frame.degraded else ""
    truth = ""
    if getattr(frame, "has_truth", False):
        from bubble_rt.io.protocol import truth_summary

        tx, ty, tz, tmag = _vec(frame.true_net_force)
        ts = truth_summary(frame)
        iou = "-" if ts["contact_iou"] is None else f"{ts['contact_iou']:.2f}"
        truth = (
            f"| true F [{tx:+7.3f} {ty:+7.3f} {tz:+7.3f}] N  |F| {tmag:6.3f} N  "
            f"contact {ts['contact_nodes']:3d} nodes IoU {iou}  "
        )
    return (
        f"#{frame.seq:<6d} {rate_hz:5.1f} Hz  lat {frame.latency_ms:6.1f} ms  "
        f"F [{fx:+7.3f} {fy:+7.3f} {fz:+7.3f}] N  |F| {mag:6.3f} N  {torque}"
        f"contact {int(frame.contact.sum()):3d} nodes {len(frame.patches)} patch  "
        f"{truth}{state}{flag}"
    )


def echo(
    address: str,
    control: str | None = None,
    sensor: str = "",
    as_json: bool = False,
    count: int = 0,
    timeout_s: float = 0.0,
    stop: Any = None,
    out: Any = None,
) -> int:
    """Print frames until ``count`` frames, ``timeout_s`` of silence or ``stop`` is set."""
    import time

    from bubble_rt.io.client import Subscriber
    from bubble_rt.io.protocol import ForceFrameData

    out = out or sys.stdout
    n = 0
    rate = RateMeter()
    state = "?"
    last = time.monotonic()
    with Subscriber(address, control=control, sensor_id=sensor) as sub:
        while (count <= 0 or n < count) and not (stop is not None and stop.is_set()):
            msg = sub.recv(0.2)
            if msg is None:
                if timeout_s > 0 and time.monotonic() - last > timeout_s:
                    print(f"bubble-rt echo: no frame for {timeout_s} s", file=sys.stderr)
                    return 1
                continue
            if not isinstance(msg, ForceFrameData):
                state = msg.state + (f" ({msg.reason})" if msg.reason else "")
                continue
            last = time.monotonic()
            n += 1
            hz = rate.add(msg.publish_time_ns)
            if as_json:
                d = msg.summary()
                d["rate_hz"] = round(hz, 2)
                d["status"] = state
                out.write(json.dumps(d) + "\n")
            else:
                out.write(format_line(msg, hz, state) + "\n")
            out.flush()
    return 0


def run(args: argparse.Namespace) -> int:
    try:
        return echo(args.address, None, args.sensor, args.json, args.count, args.timeout)
    except KeyboardInterrupt:
        return 0
