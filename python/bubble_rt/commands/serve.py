"""`bubble-rt serve`: run the streaming daemon (default: simulated demo scene, real time)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import Any

HELP = "run the force-estimation daemon and publish force frames over ZeroMQ"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from bubble_rt.io.image_codec import COLOR_CODECS

    parser.add_argument("--config", metavar="FILE", help="TOML configuration (see config dump)")
    parser.add_argument(
        "--camera", metavar="SOURCE", help="sim[:scene] | replay:<file> | realsense[:serial]"
    )
    parser.add_argument(
        "--pressure", metavar="SOURCE", help="camera | serial:<port> | constant:<Pa>"
    )
    parser.add_argument("--pub", metavar="ADDR", help="PUB address (tcp://127.0.0.1:5555)")
    parser.add_argument("--control", metavar="ADDR", help="control address (tcp://127.0.0.1:5556)")
    parser.add_argument("--sensor-id", help="sensor id used in topics")
    parser.add_argument("--mesh", help="mesh preset (coarse|medium|fine) or file")
    parser.add_argument("--estimator", choices=["fem", "frictionless"], help="estimator kind")
    parser.add_argument("--pace", choices=["realtime", "fast"], help="sim/replay pacing")
    parser.add_argument("--record", metavar="FILE", help="record inputs and outputs from start")
    parser.add_argument(
        "--overwrite", action="store_true", help="with --record: replace an existing file"
    )
    parser.add_argument(
        "--record-color",
        choices=COLOR_CODECS,
        help="colour images in recordings: jpeg (lossy, default) or png (lossless)",
    )
    parser.add_argument(
        "--echo", action="store_true", help="also print received frames (in-process subscriber)"
    )
    parser.add_argument(
        "--duration", type=float, default=0.0, help="stop after S seconds (0: run until signal)"
    )
    # ---- Foxglove and ROS 2 bags (bubble_rt.io.foxglove, bubble_rt.io.rosbag) ----
    parser.add_argument(
        "--foxglove",
        nargs="?",
        const="ws://127.0.0.1:8765",
        default=None,
        metavar="ADDR",
        help="serve a Foxglove WebSocket (default ws://127.0.0.1:8765); also into --record",
    )
    parser.add_argument("--topics", help="replay of a ROS 2 bag: its topics (see estimate)")
    parser.add_argument("--depth-unit", type=float, help="replay of a ROS 2 bag: 16UC1 m/count")
    # ---- end Foxglove and ROS 2 bags ----


def build_config(args: argparse.Namespace):
    from bubble_rt.config import DaemonConfig

    cfg = DaemonConfig.load(args.config, "--config") if args.config else DaemonConfig()
    return cfg.with_overrides(
        **{
            "camera.source": args.camera,
            "pressure.source": args.pressure,
            "network.pub": args.pub,
            "network.control": args.control,
            "sensor_id": args.sensor_id,
            "estimator.mesh": args.mesh,
            "estimator.kind": args.estimator,
            "camera.pace": args.pace,
            "recording.path": args.record,
            "recording.overwrite": True if args.overwrite else None,
            "recording.color": getattr(args, "record_color", None),
        }
    )


def run(args: argparse.Namespace) -> int:
    import logging

    from bubble_rt.config import ConfigError
    from bubble_rt.daemon.service import Daemon, DaemonError
    from bubble_rt.daemon.sources import SourceError

    logging.basicConfig(level=logging.INFO, format="bubble-rt serve: %(message)s")
    try:
        check_arguments(args)
    except ValueError as exc:
        print(f"bubble-rt serve: {exc}", file=sys.stderr)
        return 2
    try:
        cfg = build_config(args)
        check_replay_path(cfg.camera.source)
    except ConfigError as exc:
        print(f"bubble-rt serve: invalid configuration: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"bubble-rt serve: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    install_signal_handlers(stop)
    view = None
    try:
        daemon = Daemon(cfg, camera=bag_replay_source(cfg, args))
        if args.foxglove:
            from bubble_rt.daemon.foxglove_view import FoxgloveView

            view = FoxgloveView(args.foxglove)
            daemon.viewers.append(view)
            print(f"bubble-rt serve: Foxglove on {view.address}", file=sys.stderr, flush=True)
        daemon.start()
    except (DaemonError, SourceError, RuntimeError, ValueError) as exc:
        if view is not None:
            view.close()
        print(f"bubble-rt serve: {exc}", file=sys.stderr)
        return 1
    serve_until(daemon, stop, args.duration, args.echo)
    left = daemon.alive_threads()
    if left:
        # A thread still inside the C++ core when the interpreter finalises makes the C++
        # runtime abort (std::terminate): leave without finalising instead.
        print(
            f"bubble-rt serve: {', '.join(left)} still busy after the shutdown timeout; "
            "exiting without waiting for them",
            file=sys.stderr,
            flush=True,
        )
        sys.stdout.flush()
        os._exit(0)
    return 0


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse a bad address or output path before anything starts (ValueError naming the
    option): ZeroMQ endpoints, the Foxglove address, --record."""
    from bubble_rt._validate import output_file, zmq_endpoint
    from bubble_rt.io.foxglove import parse_address

    for option in ("pub", "control"):
        if getattr(args, option, None):
            zmq_endpoint(f"--{option}", getattr(args, option))
    if getattr(args, "foxglove", None):
        parse_address(args.foxglove, "--foxglove")
    if getattr(args, "record", None):
        output_file("--record", args.record)


def check_replay_path(source: str) -> None:
    """For ``replay:FILE``: a file must be a regular one (a FIFO would block the open, ignoring
    signals and --duration); a folder (Punyo, PNG, ROS 2 bag) is checked when opened. For
    ``sim:SCENE.toml``: a regular file of at most ``CONFIG_MAX_BYTES`` (read whole)."""
    from pathlib import Path

    from bubble_rt._validate import CONFIG_MAX_BYTES, regular_file
    from bubble_rt.config import split_source

    kind, arg = split_source(source)
    if not arg or not Path(arg).exists():
        return
    if kind == "replay" and not Path(arg).is_dir():
        regular_file("--camera replay:", arg)
    elif kind == "sim":
        regular_file("--camera sim:", arg, CONFIG_MAX_BYTES)


def bag_replay_source(cfg: Any, args: argparse.Namespace) -> Any:
    """A replay source with the bag options (--topics/--depth-unit), or None (the default)."""
    if not (getattr(args, "topics", None) or getattr(args, "depth_unit", None)):
        return None
    from bubble_rt.config import split_source
    from bubble_rt.daemon.sources import ReplayCamera

    kind, arg = split_source(cfg.camera.source)
    if kind != "replay":
        return None
    return ReplayCamera(
        arg,
        realtime=cfg.camera.pace == "realtime",
        loop=cfg.camera.loop,
        topics=args.topics,
        depth_unit=args.depth_unit,
    )


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set ``stop`` (the daemon then shuts down within its timeout)."""

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)


def serve_until(
    daemon: Any, stop: threading.Event, duration: float = 0.0, echo: bool = False
) -> None:
    """Run a started daemon until ``stop`` (or ``duration`` seconds), then stop it cleanly."""
    import time

    print(
        f"bubble-rt serve: sensor {daemon.config.sensor_id!r}, camera "
        f"{daemon.config.camera.source}, pressure {daemon.config.pressure.source}; publishing "
        f"on {daemon.pub_address}, control on {daemon.control_address}",
        file=sys.stderr,
        flush=True,
    )
    echo_thread = None
    if echo:
        from bubble_rt.commands.echo import echo as echo_loop

        echo_thread = threading.Thread(
            target=echo_loop,
            kwargs={"address": daemon.pub_address, "control": daemon.control_address, "stop": stop},
            daemon=True,
        )
        echo_thread.start()
    end = time.monotonic() + duration if duration > 0 else None
    try:
        while not stop.wait(0.1):
            if end is not None and time.monotonic() >= end:
                break
    finally:
        stop.set()
        daemon.stop()
        if echo_thread is not None:
            echo_thread.join(0.5)
    rec = "; recording finalised" if daemon.config.recording.path else ""
    print(
        f"bubble-rt serve: stopped after {daemon.frames_published} frames "
        f"({daemon.frames_dropped} dropped){rec}",
        file=sys.stderr,
        flush=True,
    )
