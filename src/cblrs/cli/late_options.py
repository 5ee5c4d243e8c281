"""Options of ``cblrs matcher`` for messages that arrive late, and for when they do not.

``--late-horizon`` and ``--late-delay`` set the
:class:`~cblrs.runtime.matcher.retrack.RetrackPolicy`:
how far back late messages are still tracked (by re-tracking from a snapshot taken before
them) and how long the matcher waits for a burst of them to end. ``--camera-fps`` tells the
ordering the cameras' frame rate, so that a camera's first frames are released without
waiting for its next ones (a camera faster than that is noticed at its second frame, which
could then come late, and is re-tracked).
"""

from __future__ import annotations

import argparse
from typing import Any

from cblrs.cli.common import check_non_negative, check_positive


def add_late_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--late-horizon``, ``--late-delay`` and ``--camera-fps``."""
    late = parser.add_argument_group(
        "late messages", "tracked by re-tracking from a snapshot taken before them (tracks "
        "published again with corrected_from)")
    late.add_argument("--late-horizon", type=float, default=10.0, metavar="MINUTES",
                      help="how far back late messages are still tracked (snapshots are kept "
                      "that long; default 10; 0: late messages are stored, never tracked)")
    late.add_argument("--late-delay", type=float, default=1.0, metavar="SECONDS",
                      help="re-track once no late message came for this long (default 1)")
    late.add_argument("--camera-fps", type=float, metavar="FPS",
                      help="the cameras' frame rate (the fastest's), if known: a camera's first "
                      "frames are then tracked without waiting for its next ones, until its "
                      "own frame period is measured (default: unknown; they wait)")


def camera_fps(args: argparse.Namespace) -> float | None:
    """``--camera-fps``, checked (a finite number > 0), or None.

    Raises:
        UsageError: zero, negative or not finite.
    """
    if args.camera_fps is None:
        return None
    return check_positive(args.camera_fps, "--camera-fps")


def retrack_policy(args: argparse.Namespace) -> Any:
    """The :class:`~cblrs.runtime.matcher.retrack.RetrackPolicy` of the options; None: off.

    Raises:
        UsageError: a negative or non-finite value.
    """
    check_non_negative(args.late_horizon, "--late-horizon")
    check_non_negative(args.late_delay, "--late-delay")
    if args.late_horizon == 0:
        return None
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.matcher.retrack import RetrackPolicy

    return RetrackPolicy(horizon_s=args.late_horizon * 60, delay_s=args.late_delay)
