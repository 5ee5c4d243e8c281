"""Entry point of the ``cblrs`` command.

Each subcommand lives in its own module of this package and provides::

    def register(subparsers) -> None   # adds its parser, sets `handler=run`
    def run(args) -> int               # does the work, returns the exit code

User mistakes (:class:`cblrs.errors.CblrsError`, :class:`UsageError`) are printed as one
sentence on stderr with a non-zero exit code; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cblrs import __version__
from cblrs.cli.common import UsageError
from cblrs.errors import CblrsError

# Subcommand modules, in the order `cblrs --help` lists them.
SUBCOMMANDS = [
    "demo",
    "site",
    "calibrate",
    "render",
    "locate",
    "show",
    "track",
    "eval",
    "analytics",
    "broker_config",
    "camera",
    "matcher",
    "bench",
    "experiment",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cblrs",
        description="Privacy-preserving multi-camera localisation with colour reference images.",
    )
    parser.add_argument("--version", action="version", version=f"cblrs {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"cblrs.cli.{name}").register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except (CblrsError, UsageError) as error:
        print(f"cblrs {args.command}: error: {error}", file=sys.stderr)
        return 2 if isinstance(error, UsageError) else 1
    except KeyboardInterrupt:
        print(f"cblrs {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
