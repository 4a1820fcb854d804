"""`bubble-rt config dump|check`: print the default daemon configuration, or validate a file."""

from __future__ import annotations

import argparse
import sys

HELP = "print the default daemon configuration (TOML) or check a configuration file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "action",
        choices=["dump", "check"],
        help="dump: print the defaults (or FILE with defaults filled in), each key commented with "
        "its documentation and range; check: validate FILE",
    )
    parser.add_argument("file", nargs="?", help="a TOML configuration file")


def run(args: argparse.Namespace) -> int:
    from bubble_rt.config import ConfigError, DaemonConfig, dump_toml

    try:
        cfg = (
            DaemonConfig.load(args.file, f"config {args.action} FILE")
            if args.file
            else DaemonConfig()
        )
    except ConfigError as exc:
        print(f"bubble-rt config: invalid configuration: {exc}", file=sys.stderr)
        return 2
    if args.action == "dump":
        sys.stdout.write(dump_toml(cfg))
    else:
        if not args.file:
            print("bubble-rt config check: give a FILE to check", file=sys.stderr)
            return 2
        print(f"{args.file}: ok")
    return 0
