"""The `monovoc` command line: one subcommand per job (see `monovoc --help`)."""

from __future__ import annotations

import argparse
import importlib
import sys

# Each module under monovoc_ros.commands defines `register(subparsers)`, adding its subcommand(s)
# with `set_defaults(func=...)`; the function returns the process exit code.
COMMAND_MODULES: list[str] = [
    "map",
    "segment",
    "eval",
    "bag",
    "replay",
    "record",
    "query",
    "ask",
    "approach",
    "eval_retrieval",
    "demo",
    "merge",
    "warm_up",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="monovoc",
        description="MonoVoc: open-vocabulary object-level semantic maps on 3D Gaussian Splatting maps.",
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"monovoc_ros.commands.{name}").register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except OSError as exc:  # a path it cannot read or write (a file where a folder goes, no permission): one line
        command = " ".join(c for c in (args.command, getattr(args, "bag_command", None)) if c)  # bag's sub-commands
        print(f"monovoc {command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
