"""`bubble-rt` command line: one subcommand per module in bubble_rt.commands.

Each command module provides ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports happen inside ``run`` so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = [
    "serve",
    "echo",
    "record",
    "recover",
    "config",
    "estimate",
    "simulate",
    "eval",
    "calibrate",
    "bench",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bubble-rt", description=__doc__.splitlines()[0])
    from bubble_rt import __version__

    parser.add_argument("--version", action="version", version=f"bubble-rt {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        mod = importlib.import_module(f"bubble_rt.commands.{name}")
        p = sub.add_parser(
            name, help=mod.HELP, description=mod.HELP, epilog=getattr(mod, "EPILOG", None)
        )
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    from bubble_rt._validate import PathError

    try:
        return int(args._run(args) or 0)
    except PathError as exc:  # a path that is not a regular file, named by its option
        print(f"bubble-rt {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
