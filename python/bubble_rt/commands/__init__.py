"""Subcommands of `bubble-rt` (see bubble_rt.cli)."""
