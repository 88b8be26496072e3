"""The ``ooi-seg`` command line: one subcommand per module in this package.

Each module ``ooi_seg_ros.cli.<name>`` defines ``register(subparsers)`` which adds its parser
and sets ``func`` (a callable taking the parsed args and returning an exit code).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ..core.types import OoiSegError

SUBCOMMANDS = ("info", "simulate", "sfm", "segment", "eval", "train", "export", "play",
               "record", "recover", "run")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ooi-seg",
        description="Object-of-interest segmentation and object-only Gaussian splatting.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            mod = importlib.import_module(f"ooi_seg_ros.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"ooi_seg_ros.cli.{name}":
                continue  # subcommand not built yet
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if not logging.getLogger().handlers:
        # library warnings (e.g. the SfM's) print once, named, on stderr
        logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                            format="[%(name)s] %(levelname)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except OoiSegError as exc:
        print(f"ooi-seg {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"ooi-seg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
