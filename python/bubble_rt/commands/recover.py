"""`bubble-rt recover IN [-o OUT]`: rewrite a cut or damaged MCAP recording as a finalised one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "rewrite an MCAP recording that was not closed (crash, kill, full disk) as a finalised file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="the MCAP file to read (left unchanged)")
    parser.add_argument(
        "-o", "--output", help="the finalised, indexed file to write (default: IN.recovered.mcap)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")


def default_output(path: str | Path) -> Path:
    p = Path(path)
    return p.with_name(p.stem + ".recovered.mcap")


def run(args: argparse.Namespace) -> int:
    from bubble_rt.io.mcap import RecordingPathError, recover
    from bubble_rt.io.mcap_scan import McapFileError

    out = Path(args.output) if args.output else default_output(args.input)
    try:
        report = recover(args.input, out, overwrite=args.overwrite)
    except (McapFileError, RecordingPathError, OSError) as exc:
        print(f"bubble-rt recover: {exc}", file=sys.stderr)
        return 1
    state = "was closed" if report.closed else "was not closed"
    print(f"{args.input} {state}: {report.summary(hint=False)}")
    for problem in report.problems[:20]:
        print(f"  {problem}")
    if len(report.problems) > 20:
        print(f"  ... and {len(report.problems) - 20} more")
    print(f"wrote {report.messages - report.messages_undecodable} messages to {out}")
    return 0
