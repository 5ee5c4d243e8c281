"""``cblrs site``: write (init), validate (check) and bundle (export) a site file."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from cblrs.cli.common import UsageError, add_dataset_argument, add_output_options, print_json


def register(subparsers) -> None:
    """Add the ``cblrs site`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "site",
        help="site files: init from a dataset, check, export as one file",
        description=(
            "A site file (YAML or JSON) describes planes, cameras, a site map and places in one "
            "place; render, camera, matcher, track, eval and demo take it with --site."
        ),
    )
    actions = parser.add_subparsers(dest="site_action", metavar="ACTION")

    init = actions.add_parser(
        "init", help="write a site file for a WILDTRACK, MultiviewX or AI City folder"
    )
    add_dataset_argument(
        init, "WILDTRACK, MultiviewX or AI City folder", required=True, positional_alias=True
    )
    init.add_argument("--out", type=Path, required=True, help="site file to write (.yaml/.json)")
    init.add_argument(
        "--inline",
        action="store_true",
        help="write the cameras' parameters instead of referring to the dataset's files",
    )
    init.add_argument(
        "--plane",
        metavar="X0,Y0,WIDTH,LENGTH",
        help="ground plane in metres (default: the dataset's annotated area + 2 m, or the "
        "ground the AI City cameras see)",
    )
    init.add_argument("--bits", type=int, choices=(8, 16), default=16)
    init.add_argument("--name", help="the site's name (default: the folder's)")
    init.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    add_output_options(init)
    init.set_defaults(handler=run_init)

    check = actions.add_parser("check", help="validate a site file and say what it is ready for")
    check.add_argument("site", type=Path, metavar="SITE")
    check.add_argument(
        "--for",
        dest="needed",
        metavar="COMMANDS",
        help="comma-separated commands (render, camera, matcher, track, analytics) the site "
        "must be ready for; exit 1 otherwise",
    )
    add_output_options(check)
    check.set_defaults(handler=run_check)

    export = actions.add_parser(
        "export",
        help="write the site as one self-contained file (calibration files, points and the "
        "map image inlined)",
    )
    export.add_argument("site", type=Path, metavar="SITE")
    export.add_argument("--out", type=Path, required=True, help="file to write (.yaml/.json)")
    export.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    add_output_options(export)
    export.set_defaults(handler=run_export)

    def usage(args: argparse.Namespace) -> int:
        parser.print_help()
        return 2

    parser.set_defaults(handler=usage)


def _writable(path: Path, force: bool) -> None:
    if path.is_dir():
        raise UsageError(f"--out {path} is a folder; give a file name.")
    if path.exists() and not force:
        raise UsageError(f"--out {path} exists; pass --force to overwrite it.")


def _plane(text: str | None) -> tuple[float, float, float, float] | None:
    if text is None:
        return None
    try:
        values = [float(value) for value in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not (values[2] > 0 and values[3] > 0):
        raise UsageError(
            f"--plane {text!r} must be X0,Y0,WIDTH,LENGTH metres with a positive size."
        )
    return (values[0], values[1], values[2], values[3])


def run_init(args: argparse.Namespace) -> int:
    """Run ``cblrs site init``; the exit code."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site import load_site, save_document, site_from_dataset

    _writable(args.out, args.force)
    document = site_from_dataset(
        args.dataset,
        args.out,
        inline=args.inline,
        plane=_plane(args.plane),
        bits=args.bits,
        name=args.name,
    )
    path = save_document(document, args.out)
    site = load_site(path)  # what was written must read back
    summary = {
        "out": str(path),
        "name": site.name,
        "cameras": site.camera_names,
        "planes": site.planes.to_list() if site.planes is not None else [],
    }
    if args.json:
        print_json(summary)
    else:
        plane = site.planes[0] if site.planes is not None else None
        extent = (
            f", plane {plane.width:g} x {plane.length:g} m at ({plane.origin[0]:g}, "
            f"{plane.origin[1]:g})"
            if plane is not None
            else ""
        )
        print(
            f"wrote {path}: {len(site.camera_names)} cameras{extent}; check it with "
            f"`cblrs site check {path}`"
        )
    return 0


def run_check(args: argparse.Namespace) -> int:
    """Run ``cblrs site check``; the exit code (1 when not ready)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site.check import COMMANDS, check_site, format_check

    needed = []
    if args.needed:
        needed = [name.strip() for name in re.split(r"[,\s]+", args.needed) if name.strip()]
        unknown = [name for name in needed if name not in COMMANDS]
        if unknown:
            raise UsageError(f"--for {unknown[0]!r} is not one of {', '.join(COMMANDS)}.")
    report = check_site(args.site)
    if args.json:
        print_json(report)
    else:
        print(format_check(report))
    if not report["valid"] or any(not camera["ok"] for camera in report["cameras"]):
        return 1
    return 1 if any(not report["ready"][name] for name in needed) else 0


def run_export(args: argparse.Namespace) -> int:
    """Run ``cblrs site export``; the exit code."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site import load_site, save_document

    _writable(args.out, args.force)
    if args.out.resolve() == args.site.resolve():
        raise UsageError("--out must differ from the site file it exports.")
    site = load_site(args.site)
    path = save_document(site.export(), args.out)
    load_site(path)
    if args.json:
        print_json({"out": str(path), "cameras": list(site.camera_names)})
    else:
        print(f"wrote {path}: {len(site.camera_names)} cameras, self-contained")
    return 0
