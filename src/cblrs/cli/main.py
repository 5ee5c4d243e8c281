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
    "dashboard",
    "bench",
    "experiment",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cblrs",
        description="Privacy-preserving multi-camera localisation with colour reference images.",
    )
    parser.add_argument("--version", action="version", version=f"cblrs {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0,
        help="-v: debug messages of cblrs; -vv: also every MQTT packet (paho)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"cblrs.cli.{name}").register(subparsers)
    return parser


LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%Y-%m-%dT%H:%M:%S"


def configure_logging(verbosity: int, quiet: bool = False) -> None:
    """Timestamped lines on stderr. cblrs logs its lifecycle at INFO (connections,
    reconnections, cameras online/offline, rejections at most once per reason every few
    seconds); other libraries only warnings. ``--quiet``: cblrs warnings only; ``-v``: cblrs
    at DEBUG; ``-vv``: paho's packet log too."""
    # A no-op where logging is configured already (a program embedding the CLI, pytest).
    logging.basicConfig(level=logging.WARNING, format=LOG_FORMAT, datefmt=LOG_DATE_FORMAT)
    level = logging.WARNING if quiet else logging.INFO
    logging.getLogger("cblrs").setLevel(logging.DEBUG if verbosity >= 1 else level)
    paho = logging.getLogger("cblrs.runtime.transport.paho")
    paho.setLevel(logging.DEBUG if verbosity >= 2 else logging.INFO)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, quiet=bool(getattr(args, "quiet", False)))
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
