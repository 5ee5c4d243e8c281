"""``cblrs analytics``: line counts, zone visits and dwell, OD and heatmap of a tracks file."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cblrs.analytics.config import AnalyticsConfig, AnalyticsError
from cblrs.analytics.files import analyse_file
from cblrs.cli.common import UsageError, add_output_options, format_table, print_json


def register(subparsers) -> None:
    """Add the ``cblrs analytics`` parser to ``subparsers``."""
    defaults = AnalyticsConfig()
    parser = subparsers.add_parser(
        "analytics",
        help="counts per line and direction, zone entries/exits/dwell, OD, heatmap",
        description=(
            "Count what operators count, from global tracks (AI City 2024 text format) and "
            "the places of a site file: crossings of each counting line per direction and "
            "class (counted once, with spatial hysteresis), zone entries, exits, occupancy "
            "over time and dwell per visit (short exits merged), the origin-destination "
            "matrix between zones, and an occupancy heatmap (person-seconds per cell). "
            "Writes CSV/JSON tables and PNG plots into --out."
        ),
    )
    parser.add_argument("tracks", type=Path, metavar="TRACKS.txt", help="tracks file")
    parser.add_argument("--site", type=Path, required=True, metavar="SITE.yaml",
                        help="site file with a places: section (zones, lines)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="folder for the tables and plots")
    parser.add_argument("--fps", type=float, default=None, metavar="F",
                        help="frames per second of the file's frame numbers "
                        "(default: from its .meta.json sidecar: the frame rate, or the capture "
                        "times that cblrs matcher --out-tracks keeps)")
    parser.add_argument("--interval", type=float, default=None, metavar="S",
                        help="time bin of the counts over time, seconds (default: from the "
                        "span); with a site timezone it must divide a day, and bins start on "
                        "the local clock (an hour at hh:00, a day at midnight)")
    parser.add_argument("--start", default=None, metavar="TIME",
                        help="the time of the file's second 0 when its times are scene "
                        "seconds (frame numbers / --fps): an ISO time such as "
                        "2026-03-29T06:00:00 (in the site's timezone unless it has an offset) "
                        "or epoch seconds; needed for local times and opening hours")
    parser.add_argument("--cell", type=float, default=0.5, metavar="M",
                        help="heatmap cell, metres (default 0.5)")
    parser.add_argument("--line-hysteresis", type=float, default=defaults.line_hysteresis_m,
                        metavar="M", help="metres past a line on each side for a crossing "
                        f"(default {defaults.line_hysteresis_m:g}; a line's own setting wins)")
    parser.add_argument("--line-rule", choices=("hysteresis", "side_change"),
                        default=defaults.line_rule,
                        help="what counts as crossing a line: hysteresis (default: from "
                        "beyond --line-hysteresis on one side to beyond it on the other, "
                        "through the segment) or side_change (common tools' rule, e.g. "
                        "supervision's LineZone: any change of side within the segment's "
                        "extent); a line's own rule: wins")
    parser.add_argument("--zone-hysteresis", type=float, default=defaults.zone_hysteresis_m,
                        metavar="M", help="metres past a zone border to count as in or out "
                        f"(default {defaults.zone_hysteresis_m:g})")
    parser.add_argument("--merge-gap", type=float, default=defaults.merge_gap_s, metavar="S",
                        help="exits shorter than this continue the visit "
                        f"(default {defaults.merge_gap_s:g} s)")
    parser.add_argument("--lost-after", type=float, default=defaults.lost_after_s, metavar="S",
                        help="a track unseen this long has ended "
                        f"(default {defaults.lost_after_s:g} s)")
    parser.add_argument("--min-track", type=float, default=defaults.min_track_s, metavar="S",
                        help="tracks shorter-lived than this count nothing "
                        f"(default {defaults.min_track_s:g} s)")
    parser.add_argument("--no-plots", action="store_true", help="tables only")
    add_output_options(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs analytics`` with its parsed arguments; the exit code."""
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder.")
    try:
        config = AnalyticsConfig(
            line_hysteresis_m=args.line_hysteresis, line_rule=args.line_rule,
            zone_hysteresis_m=args.zone_hysteresis,
            merge_gap_s=args.merge_gap, lost_after_s=args.lost_after,
            min_track_s=args.min_track,
            **({} if args.interval is None else {"interval_s": args.interval}),
        )
    except AnalyticsError as error:
        raise UsageError(str(error)) from None
    if not args.cell > 0:
        raise UsageError(f"--cell must be a positive number of metres, got {args.cell}.")
    start = None
    if args.start is not None:
        start = _start_time(args.start, args.site)
    summary = analyse_file(args.tracks, args.site, args.out, frames_per_second=args.fps,
                           config=config, cell_m=args.cell, plots=not args.no_plots,
                           start=start)
    if args.json:
        print_json(summary)
        return 0
    print(f"{summary['rows']} rows, {summary['track_ids']} track ids, "
          f"{summary['seconds']:.1f} s on site {summary['site']}; local time: "
          f"{summary['local_time']}")
    if summary["closed_events"]:
        print(f"not counted, outside opening hours: {summary['closed_events']} events")
    if summary["lines"]:
        rows: dict[str, dict[str, Any]] = {}
        for row in summary["lines"]:
            rows.setdefault(row["line"], {"rule": row["rule"]})[row["direction"]] = row["count"]
        print(format_table(["line", "positive", "negative", "counted when"],
                           [[name, c.get("positive", 0), c.get("negative", 0), c["rule"]]
                            for name, c in rows.items()]))
    if summary["zones"]:
        print(format_table(
            ["zone", "entries", "exits", "visits", "mean dwell s", "person-s"],
            [[z["zone"], z["entries"], z["exits"], z["visits"], z["mean_dwell_s"],
              z["person_seconds"]] for z in summary["zones"]]))
    print(f"wrote {len(summary['files'])} files to {args.out}")
    return 0


def _start_time(text: str, site_path: Path) -> float:
    """Epoch seconds of ``--start`` (an ISO time without offset is in the site's zone)."""
    from cblrs.localtime import LocalTimeError, parse_time
    from cblrs.site import load_site

    try:
        return parse_time(text, load_site(site_path).calendar)
    except LocalTimeError as error:
        raise UsageError(f"--start: {str(error).rstrip('.')}.") from None
