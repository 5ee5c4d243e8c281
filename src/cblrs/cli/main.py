"""Entry point of the ``cblrs`` command.

Each subcommand lives in its own module of this package and provides::

    def register(subparsers) -> None   # adds its parser, sets `handler=run`
    def run(args) -> int               # does the work, returns the exit code

Exit codes, the same for every subcommand: 0 success; 2 a usage error (argparse's own, and
:class:`~cblrs.cli.common.UsageError`: bad or conflicting options); 1 a runtime failure
(:class:`cblrs.errors.CblrsError`, e.g. :class:`~cblrs.cli.common.InputError` for a missing
file, unreadable data, an unreachable broker); 130 interrupted. Errors are printed as one
sentence on stderr; anything else is a bug and keeps its traceback.

A service command that sets ``stop_signals=(deadline_s, watchdog exit code)`` among its
parser's defaults (``camera``, ``matcher``) gets SIGINT/SIGTERM handled by
:class:`~cblrs.cli.stopping.StopSignals` (``args.signals``): it arms it once it can stop
cleanly; a signal before that, or a second one, ends it at once with one line (exit 0 while
starting, 128 + the signal's number when a clean stop was cut short).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cblrs import __version__
from cblrs.cli.common import UsageError, resolve_dataset
from cblrs.cli.examples import decorate
from cblrs.cli.stopping import Interrupted, StopSignals
from cblrs.errors import CblrsError

# Subcommand modules, in the order `cblrs --help` lists them, with the one line `cblrs --help`
# shows for each (tests/cli check it equals the help the module registers). Only the module of
# the subcommand being run is imported: `cblrs --help` and `cblrs track` do not import the
# runtime, the dashboard or the benchmarks (see build_parser).
SUBCOMMANDS = {
    "demo": "run the whole method on a built-in synthetic world and draw the results",
    "site": "site files: init from a dataset, check, export as one file",
    "calibrate": "calibrate a camera from clicked image <-> world points (CSV u,v,x,y)",
    "render": "render colour reference images from a calibration",
    "locate": "world positions of pixels or boxes from a reference image",
    "show": "visualise a reference image with a metric grid",
    "track": "track a multi-camera dataset and write world tracks (AI City format)",
    "eval": "HOTA, DetA, AssA, LocA, MOTA, IDF1 of tracks against ground truth",
    "analytics": "counts per line and direction, zone entries/exits/dwell, OD, heatmap",
    "link": "global ids across planes from the planes' tracks (matcher databases or files)",
    "pseudo": "pseudo coordinates: make a key, a pseudo site for the matcher, map tracks back",
    "broker_config": "write a Mosquitto or NATS configuration (users, permissions, TLS) for "
    "cameras, matchers and viewers",
    "up": "start a whole site from its site file: secured broker, matchers, dashboard, "
    "cameras",
    "camera": "run an edge camera node: detections -> reference colours -> MQTT",
    "matcher": "run the central matcher of one plane: MQTT -> validate -> track -> SQLite",
    "linker": "run the site's linker: every plane's tracks -> global ids and site counts",
    "dashboard": "serve the live dashboard: site map, tracks, counts, cameras; replay; "
    "calibration",
    "dashboard_users": "the dashboard's users: add, passwd, set-role, remove, list, token, "
    "revoke",
    "bench": "benchmarks: lookup (Table I), render, claims, tracker, pipeline, track, "
    "analytics, linker, dashboard, backbone, asynchrony, mqtt, all",
    "experiment": "rerun the paper's experiments: targeting (IV-B), resolution; clicked "
    "calibration; count accuracy; pseudo-coordinate recovery; identities across planes",
}


def _command_of(argv: list[str]) -> str | None:
    """The subcommand ``argv`` runs (its first word that is not an option), or None."""
    for word in argv:
        if not word.startswith("-"):
            return word
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``cblrs`` parser, its examples and defaults shown.

    Args:
        command: the subcommand about to run: only its module is imported, the others are
            listed by their one line ("": none is imported, for ``cblrs --help``; an unknown
            word builds them all, so argparse names the choices). None builds every
            subcommand (tests, documentation).
    """
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
    known = {name.replace("_", "-") for name in SUBCOMMANDS}
    for name, summary in SUBCOMMANDS.items():
        spelled = name.replace("_", "-")
        if command is None or command == spelled or (command and command not in known):
            importlib.import_module(f"cblrs.cli.{name}").register(subparsers)
        else:
            # lazy: a stub that only lists the subcommand; its module is not imported
            subparsers.add_parser(spelled, help=summary, add_help=False)
    decorate(parser)
    return parser


LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%Y-%m-%dT%H:%M:%S"


_CONTROL = {code: f"\\x{code:02x}" for code in (*range(0x20), 0x7F, *range(0x80, 0xA0))
            if code != 0x09}
_CONTROL.update({0x0A: "\\n", 0x0D: "\\r", 0x2028: "\\u2028", 0x2029: "\\u2029"})


class OneLineFormatter(logging.Formatter):
    """A record is one line: control characters in its message are escaped (``\\n``,
    ``\\x1b``), so a name or path a client chose (a URL's ``%0A``, a name on the wire) cannot
    add a line of its own to the log, which is the services' audit trail, nor move the
    terminal's cursor. An exception's traceback still follows on lines of its own."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        return super().formatMessage(record).translate(_CONTROL)


def configure_logging(verbosity: int, quiet: bool = False) -> None:
    """Timestamped lines on stderr, one per record (:class:`OneLineFormatter`). cblrs logs
    its lifecycle at INFO (connections, reconnections, cameras online/offline, rejections at
    most once per reason every few seconds); other libraries only warnings. ``--quiet``:
    cblrs warnings only; ``-v``: cblrs at DEBUG; ``-vv``: paho's packet log too."""
    # A no-op where logging is configured already (a program embedding the CLI, pytest).
    handler = logging.StreamHandler()
    handler.setFormatter(OneLineFormatter(LOG_FORMAT, LOG_DATE_FORMAT))
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    level = logging.WARNING if quiet else logging.INFO
    logging.getLogger("cblrs").setLevel(logging.DEBUG if verbosity >= 1 else level)
    paho = logging.getLogger("cblrs.runtime.transport.mqtt_transport.paho")
    paho.setLevel(logging.DEBUG if verbosity >= 2 else logging.INFO)


def main(argv: list[str] | None = None) -> int:
    """Run ``cblrs`` with ``argv`` (default: the process's); the exit code."""
    words = sys.argv[1:] if argv is None else list(argv)
    command = _command_of(words)
    parser = build_parser(command if command is not None else "")
    args = parser.parse_args(words)
    configure_logging(args.verbose, quiet=bool(getattr(args, "quiet", False)))
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    signals = None
    if getattr(args, "stop_signals", None) is not None:
        deadline_s, code = args.stop_signals
        signals = args.signals = StopSignals(f"cblrs {args.command}", deadline_s,
                                             lambda: code).install()
    try:
        resolve_dataset(args)
        return int(args.handler(args) or 0)
    except (CblrsError, UsageError) as error:
        print(f"cblrs {args.command}: error: {error}", file=sys.stderr)
        return 2 if isinstance(error, UsageError) else 1
    except KeyboardInterrupt:
        print(f"cblrs {args.command}: interrupted", file=sys.stderr)
        return 130
    except Interrupted as interrupted:
        armed = signals is not None and signals.armed
        print(f"cblrs {args.command}: stopped by {interrupted.name} "
              + ("at once (a second signal)." if armed else "while starting."), file=sys.stderr)
        return interrupted.exit_code if armed else 0
    except BrokenPipeError:
        return 0
    finally:
        if signals is not None:
            signals.restore()


if __name__ == "__main__":
    sys.exit(main())
