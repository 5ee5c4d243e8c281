"""``cblrs link``: global ids across planes from every plane's tracks, offline."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cblrs.cli.common import InputError, UsageError, add_output_options, format_table, print_json


def register(subparsers) -> None:
    """Add the ``cblrs link`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "link",
        help="global ids across planes from the planes' tracks (matcher databases or files)",
        description=(
            "Give every person or vehicle one id across the site's planes: a plane's track "
            "that starts where the site file's links say tracks arrive from a neighbouring "
            "plane (an overlap band, a portal) continues that plane's track, matched by time, "
            "position and velocity. The same linker as `cblrs linker`, fed the stored tracks "
            "at once: the result equals the live one on the same rows. Writes the global "
            "tracks (AI City format, track id = global id) and, with --analytics, the site's "
            "counts on them (lives that span the portals' transit)."
        ),
    )
    parser.add_argument("--site", type=Path, required=True, metavar="SITE.yaml",
                        help="site file with planes and links")
    parser.add_argument("--plane", action="append", default=[], metavar="ID=FILE",
                        help="a plane's tracks: its matcher's database (exact capture times) "
                        "or an AI City tracks file (repeat for every plane)")
    parser.add_argument("--out", type=Path, required=True, metavar="TRACKS.txt",
                        help="the global tracks (AI City format) and its .meta.json sidecar")
    parser.add_argument("--handovers", type=Path, metavar="FILE.csv",
                        help="also write every hand-over (CSV)")
    parser.add_argument("--analytics", type=Path, metavar="DIR",
                        help="also count the site's places on the global tracks into DIR")
    parser.add_argument("--fps", type=float, metavar="F",
                        help="frame rate of AI City files without a sidecar")
    add_output_options(parser)
    parser.set_defaults(handler=run)


def parse_planes(items: list[str]) -> dict[int, Path]:
    """``ID=FILE`` items -> {plane id: file}; UsageError for a malformed or repeated one."""
    planes: dict[int, Path] = {}
    for item in items:
        plane, separator, path = item.partition("=")
        if not separator or not plane.strip().isdigit() or not path:
            raise UsageError(f"--plane {item!r} must be ID=FILE, e.g. 1=plane1.db.")
        plane_id = int(plane)
        if plane_id in planes:
            raise UsageError(f"--plane {plane_id} is given twice.")
        planes[plane_id] = Path(path)
    if not planes:
        raise UsageError("give every plane's tracks with --plane ID=FILE (repeat it).")
    return planes


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs link`` with its parsed arguments; the exit code."""
    inputs = parse_planes(args.plane)
    if args.fps is not None and not args.fps > 0:
        raise UsageError(f"--fps must be a positive number, got {args.fps}.")
    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give a file.")
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.aicity import write_tracks
    from cblrs.linking.files import (
        frames_per_second_of,
        link_site,
        read_plane_tracks,
        site_analytics_config,
    )
    from cblrs.site import load_site

    site = load_site(args.site)
    planes = site.require_planes("linking")
    if not site.links:
        raise InputError(f"{args.site} has no links between its planes (links: in the site "
                         "file), so no track can pass from one plane to another.")
    per_plane = {plane: read_plane_tracks(path, args.fps) for plane, path in inputs.items()}
    result = link_site(planes, site.links, per_plane)
    rate = args.fps or frames_per_second_of(per_plane)
    write_tracks(args.out, result.rows.tracks, frames_per_second=rate)
    summary = {"out": str(args.out), **result.summary()}
    if args.handovers is not None:
        lines = ["global_id,timestamp,from_plane,from_track,to_plane,to_track,kind,score"]
        lines += [f"{item.global_id},{item.timestamp!r},{item.from_plane},{item.from_track},"
                  f"{item.to_plane},{item.to_track},{item.kind},{item.score:.4f}"
                  for item in result.handovers]
        from cblrs.analytics.tables import open_private

        with open_private(args.handovers, "w") as handle:  # who went where: the owner's only
            handle.write("\n".join(lines) + "\n")
        summary["handovers_file"] = str(args.handovers)
    if args.analytics is not None:
        if not len(site.places):
            raise InputError(f"{args.site} has no places to count (places: zones, lines).")
        from cblrs.analytics.tables import analyse_tracks, write_result

        config = site_analytics_config(site.links)
        counted = analyse_tracks(result.rows.tracks, site.places, config)
        write_result(counted, args.analytics)
        summary["analytics"] = {"out": str(args.analytics), "lost_after_s": config.lost_after_s,
                                "od": counted.od}
    if args.json:
        print_json(summary)
        return 0
    print(format_table(["plane", "tracks", "rows"],
                       [[plane, figures["tracks"], figures["rows"]]
                        for plane, figures in summary["planes"].items()]))
    print(f"{summary['rows']} global rows, {summary['global_ids']} global ids, hand-overs: "
          f"{json.dumps(summary['handovers'])}; wrote {args.out}")
    return 0
