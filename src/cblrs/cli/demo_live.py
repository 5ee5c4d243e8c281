"""``cblrs demo``'s live part: after the offline results, the plaza scene as a live site.

On a terminal (or with ``--live-seconds``), ``cblrs demo`` writes a site file whose four
cameras replay the synthetic plaza's boxes (:func:`cblrs.up.scene_site.write_scene_site`)
and runs ``cblrs up`` on it: a secured broker (Mosquitto when installed, else the NATS server
from PyPI), the matcher, the dashboard (its login link is printed) and the cameras, until
Ctrl-C. Without a terminal (tests, CI, pipes) it stops after the offline part, so nothing
waits for a Ctrl-C that never comes; ``--no-live`` does the same on a terminal.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import pwd
import shutil
import sys
from pathlib import Path
from typing import Any

from cblrs.cli.common import UsageError

LIVE_FOLDER = "live"


def add_live_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-live``, ``--live-seconds`` and ``--live-backbone``."""
    group = parser.add_argument_group("the live site (after the offline part)")
    group.add_argument("--no-live", action="store_true",
                       help="stop after the offline part (the default without a terminal)")
    group.add_argument("--live-seconds", type=float, metavar="SECONDS",
                       help="run the live site even without a terminal, and stop it SECONDS "
                       "after it runs (tests, CI, measurements)")
    group.add_argument("--live-backbone", choices=("auto", "mqtt", "nats"), default="auto",
                       help="the live site's broker: Mosquitto when installed, else NATS "
                       "(default auto)")


def wants_live(args: argparse.Namespace) -> bool:
    """Whether the demo goes on to the live site (see the module docstring).

    Raises:
        UsageError: contradictory options.
    """
    if args.live_seconds is not None:
        if not args.live_seconds > 0:
            raise UsageError("--live-seconds must be a positive number of seconds.")
        if args.no_live or args.json or args.dataset:
            raise UsageError("--live-seconds goes without --no-live, --json and --dataset.")
        return True
    if args.no_live or args.json or args.dataset:
        return False
    try:
        return sys.stdin.isatty() and sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False


def missing_for_live() -> str | None:
    """What the live site lacks (one sentence), or None."""
    if importlib.util.find_spec("uvicorn") is None:
        return ("The live site needs the dashboard and a broker: pip install -e \".[live]\" "
                "(then cblrs demo again).")
    return None


def run_live(args: argparse.Namespace, out: Path, scene: Any) -> int:
    """Write the plaza's live site into ``out/live`` and run ``cblrs up`` on it; its exit code
    (0 when the live site cannot run here: the offline part succeeded, and one sentence
    says what to install)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.cli.main import main
    from cblrs.up.host import port_is_free
    from cblrs.up.plan import DEFAULT_DASHBOARD_PORT
    from cblrs.up.scene_site import write_scene_site

    missing = missing_for_live()
    if missing is not None:
        print(missing, flush=True)
        return 0
    folder = out / LIVE_FOLDER
    state = folder / "state"
    shutil.rmtree(state, ignore_errors=True)  # each demo's replay starts at its beginning
    site = write_scene_site(scene, folder)
    print(f"\nLive: the {scene.name} scene's {len(scene.cameras)} cameras replayed in real "
          f"time through a live site (site file {site}).\nOpen the dashboard link below in a "
          "browser for the live map; Ctrl-C stops everything.", flush=True)
    port = DEFAULT_DASHBOARD_PORT if port_is_free(DEFAULT_DASHBOARD_PORT) else 0
    # The broker runs as the demo's user: as root, Mosquitto would switch to its own user,
    # which cannot enter a home folder (e.g. /root) to read the demo's files.
    user = pwd.getpwuid(os.geteuid()).pw_name
    argv = ["up", str(site), "--out", str(state), "--backbone", args.live_backbone,
            "--dashboard-port", str(port), "--status-interval", "30", "--run-as", user]
    if args.live_seconds is not None:
        argv += ["--stop-after", repr(args.live_seconds)]
    if args.quiet:
        argv.append("--quiet")
    return main(argv)
