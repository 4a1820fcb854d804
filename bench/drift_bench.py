"""Drift and re-zeroing (issue 20): the daemon on the ``drift`` scene, re-zeroing on and off.

The scene plays an hour of drift (3.5 K of gas warming, a 0.3 %/h leak, LED warm-up) in a
minute of frames (``rates.time_scale = 60``), untouched except for one press at the start and
the same press at the end. The daemon runs it live (real time, one pass) in this process; a
viewer collects every published frame with the simulator's truth. Reported per run:

* untouched frames (the truth has no force): how many read |f| > 0.2 N or any contact node,
  and the largest |f|;
* the two presses (their held part): median estimated and true |f|, and how the end press's
  reading compares with the start press's (estimate / truth at the end over the same at the
  start, minus 1: the drift's effect on a reading; the true force itself changes, since the
  warmer gas stiffens the bubble);
* re-zero steps and the drift followed (Pa).

The re-zeroing settings scale the real-time ones by the compression: a 60 s time constant
becomes 1 s here (the hold-off stays 2 s: presses happen at scene speed).

    PYTHONPATH=python OPENBLAS_NUM_THREADS=1 python3 bench/drift_bench.py [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np
from bubble_rt.config import DaemonConfig
from bubble_rt.daemon.service import Daemon

#: Scene-time windows (s) of the two presses' held parts (bubble_rt/scenes/drift.toml).
START_PRESS = (7.4, 8.4)
END_PRESS = (58.4, 59.4)
UNTOUCHED_LIMIT_N = 0.2


class Collector:
    """A daemon viewer keeping (frame index, estimated force, contact nodes, true force)."""

    def __init__(self) -> None:
        self.rows: list[tuple[int, NDArrayLike, int, NDArrayLike]] = []
        self.reasons: dict[str, int] = {}

    def on_frame(self, frame: Any, msg: Any, mesh: Any, rec: Any) -> None:
        for r in msg.degraded_reasons:
            key = r.split("(")[0].strip()
            self.reasons[key] = self.reasons.get(key, 0) + 1
        truth = getattr(frame, "truth", None)
        if truth is None:
            return
        self.rows.append(
            (
                int(frame.index),
                np.asarray(msg.net_force, dtype=float),
                int(np.count_nonzero(np.asarray(msg.contact))),
                np.asarray(truth.net_force, dtype=float),
            )
        )

    def on_status(self, msg: Any, rec: Any) -> None:
        pass

    def close(self) -> None:
        pass


NDArrayLike = Any


def run(auto_zero: bool, scene: str, timeout_s: float) -> dict[str, Any]:
    cfg = DaemonConfig().with_overrides(
        **{
            "camera.source": f"sim:{scene}",
            "camera.loop": False,
            "camera.sim_prerender": False,
            "network.pub": "tcp://127.0.0.1:*",
            "network.control": "tcp://127.0.0.1:*",
            "auto_zero.enabled": auto_zero,
            "auto_zero.time_constant_s": 1.0,
            "auto_zero.interval_s": 0.25,
            "auto_zero.holdoff_s": 2.0,
        }
    )
    d = Daemon(cfg)
    col = Collector()
    d.viewers.append(col)
    d.start()
    from bubble_rt.sim.scene import load_scene

    sc = load_scene(scene)
    last = sc.frames - 1
    end = time.monotonic() + timeout_s
    n_seen, t_seen = 0, time.monotonic()
    try:
        while time.monotonic() < end:
            if col.rows and col.rows[-1][0] >= last - 2:
                break
            if len(col.rows) != n_seen:
                n_seen, t_seen = len(col.rows), time.monotonic()
            elif n_seen and time.monotonic() - t_seen > 20.0:  # the scene ended (last dropped)
                break
            time.sleep(0.2)
        time.sleep(0.5)
        status = d.status_message()
    finally:
        d.stop()
    hz = sc.rates.camera_hz
    idx = np.array([r[0] for r in col.rows])
    f_est = np.array([np.linalg.norm(r[1]) for r in col.rows])
    n_contact = np.array([r[2] for r in col.rows])
    f_true = np.array([np.linalg.norm(r[3]) for r in col.rows])
    t = idx / hz
    untouched = f_true < 1e-9
    bad = untouched & ((f_est > UNTOUCHED_LIMIT_N) | (n_contact > 0))

    def press(w: tuple[float, float]) -> tuple[float, float]:
        m = (t >= w[0]) & (t <= w[1])
        return float(np.median(f_est[m])), float(np.median(f_true[m]))

    (es, ts), (ee, te) = press(START_PRESS), press(END_PRESS)
    first_bad = float(t[bad][0]) if bad.any() else None
    return {
        "auto_zero": auto_zero,
        "frames": int(len(idx)),
        "frames_dropped": int(status.frames_dropped),
        "untouched_frames": int(untouched.sum()),
        "untouched_bad_frames": int(bad.sum()),
        "untouched_first_bad_scene_s": first_bad,
        "untouched_max_force_n": float(f_est[untouched].max()) if untouched.any() else 0.0,
        "untouched_contact_frames": int((untouched & (n_contact > 0)).sum()),
        "start_press_est_n": es,
        "start_press_true_n": ts,
        "end_press_est_n": ee,
        "end_press_true_n": te,
        "end_vs_start_reading": (ee / te) / (es / ts) - 1.0,
        "end_vs_start_estimate": ee / es - 1.0,
        "end_vs_start_truth": te / ts - 1.0,
        "rezero_count": int(status.rezero_count),
        "drift_followed_pa": float(status.drift_pa),
        "degraded_reasons": col.reasons,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="drift")
    ap.add_argument("--timeout", type=float, default=240.0, help="per run (s)")
    ap.add_argument("--only", choices=("on", "off"), help="run one setting only")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    out = []
    for on in (True, False):
        if args.only and (args.only == "on") != on:
            continue
        r = run(on, args.scene, args.timeout)
        out.append(r)
        print(json.dumps(r, indent=1), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
