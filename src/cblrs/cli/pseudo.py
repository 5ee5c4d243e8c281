"""``cblrs pseudo``: pseudo coordinates — make a key, a pseudo site for the matcher, map tracks
back to the site (see ``docs/privacy.md``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cblrs.cli.common import UsageError, add_output_options, format_table, print_json


def register(subparsers) -> None:
    """Add the ``cblrs pseudo`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "pseudo",
        help="pseudo coordinates: make a key, a pseudo site for the matcher, map tracks back",
        description=(
            "The site owner's key turns site coordinates into pseudo coordinates by a secret "
            "rotation and translation: reference images rendered with it (cblrs render --site "
            "SITE --key KEY) make cameras send pseudo colours, the matcher is given the pseudo "
            "site (no key), and only a key holder maps tracks back. It hides coordinates from "
            "whoever knows nothing of the site; an adversary who knows the site recovers the "
            "transform (cblrs experiment pseudo measures how well)."
        ),
    )
    actions = parser.add_subparsers(dest="pseudo_action", metavar="ACTION")

    keygen = actions.add_parser("keygen", help="make a new secret key file (mode 0600)")
    keygen.add_argument("--out", type=Path, required=True, help="key file to write")
    keygen.add_argument(
        "--force", action="store_true", help="replace an existing key file (the old key's "
        "references, pseudo sites and tracks can then no longer be mapped back)"
    )
    add_output_options(keygen)
    keygen.set_defaults(handler=run_keygen)

    site = actions.add_parser(
        "site", help="write the pseudo site the matcher is given (planes, cameras, places)"
    )
    site.add_argument("site", type=Path, metavar="SITE", help="the real site file")
    site.add_argument("--key", type=Path, required=True, help="the key file")
    site.add_argument("--out", type=Path, required=True, help="pseudo site file to write")
    site.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    add_output_options(site)
    site.set_defaults(handler=run_site)

    unmap = actions.add_parser(
        "unmap", help="map a pseudo tracks file (AI City format) back to site coordinates"
    )
    unmap.add_argument("tracks", type=Path, metavar="TRACKS", help="pseudo tracks file")
    unmap.add_argument("--key", type=Path, required=True, help="the key file")
    unmap.add_argument("--out", type=Path, required=True, help="site tracks file to write")
    add_output_options(unmap)
    unmap.set_defaults(handler=run_unmap)
    parser.set_defaults(handler=lambda args: _missing_action(parser))


def _missing_action(parser: argparse.ArgumentParser) -> int:
    raise UsageError("give an action: cblrs pseudo keygen|site|unmap (see cblrs pseudo --help).")


def run_keygen(args: argparse.Namespace) -> int:
    """``cblrs pseudo keygen``."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.privacy import PseudoKey

    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give a file name.")
    key = PseudoKey.generate()
    key.save(args.out, overwrite=args.force)
    if args.json:
        print_json({"key_id": key.key_id, "out": str(args.out), "mode": "0600"})
    else:
        print(f"key {key.key_id} written to {args.out} (mode 0600); keep it with the site "
              "file, never with the matcher")
    return 0


def run_site(args: argparse.Namespace) -> int:
    """``cblrs pseudo site``."""
    from cblrs.privacy import PseudoKey, pseudo_site_document
    from cblrs.site import load_site, save_document
    from cblrs.site.core import site_from_document

    if args.out.exists() and not args.force:
        raise UsageError(f"{args.out} exists; give --force to overwrite it.")
    key = PseudoKey.load(args.key)
    site = load_site(args.site)
    if site.pseudo_key_id is not None:
        raise UsageError(f"{args.site} is already a pseudo site (key {site.pseudo_key_id}).")
    document = pseudo_site_document(site, key)
    save_document(document, args.out)
    pseudo = site_from_document(document, args.out)
    assert pseudo.planes is not None
    planes: list[dict[str, Any]] = [
        {"id": real.plane_id, "step_mm": [1000.0 * step for step in real.step],
         "pseudo_step_mm": [1000.0 * step for step in fake.step]}
        for real, fake in zip(site.require_planes("a pseudo site"), pseudo.planes, strict=True)
    ]
    positions = pseudo.camera_positions()
    if args.json:
        print_json({
            "key_id": key.key_id, "out": str(args.out), "planes": planes,
            "cameras": len(pseudo.camera_names), "cameras_with_position": len(positions),
            "places": len(pseudo.places),
        })
        return 0
    rows = [[plane["id"], "x".join(f"{step:.3g}" for step in plane["step_mm"]),
             "x".join(f"{step:.3g}" for step in plane["pseudo_step_mm"])] for plane in planes]
    print(format_table(["plane", "step mm", "pseudo step mm"], rows))
    coarser = max(
        max(plane["pseudo_step_mm"]) / max(plane["step_mm"]) for plane in planes
    )
    print(f"pseudo site for key {key.key_id} written to {args.out}: "
          f"{len(pseudo.camera_names)} cameras ({len(positions)} with a position), "
          f"{len(pseudo.places)} places; the pseudo step is up to {coarser:.2g}x the site's. "
          "Give the matcher this file, never the key.")
    return 0


def run_unmap(args: argparse.Namespace) -> int:
    """``cblrs pseudo unmap``."""
    from cblrs.datasets import read_tracks, write_tracks
    from cblrs.datasets.aicity import read_track_metadata
    from cblrs.privacy import PseudoKey, tracks_to_site

    key = PseudoKey.load(args.key)
    if args.out.resolve() == args.tracks.resolve():
        raise UsageError("--out must not be the input file.")
    tracks = read_tracks(args.tracks)
    metadata = read_track_metadata(args.tracks)
    rate = metadata.frames_per_second if metadata is not None else None
    site_tracks = tracks_to_site(tracks, key)
    write_tracks(args.out, site_tracks, frames_per_second=rate)
    if args.json:
        print_json({"rows": len(site_tracks), "key_id": key.key_id, "out": str(args.out)})
    else:
        spread = ""
        if len(site_tracks):
            low, high = site_tracks.world_xy.min(axis=0), site_tracks.world_xy.max(axis=0)
            spread = (f" (site x {low[0]:.1f}..{high[0]:.1f} m, "
                      f"y {low[1]:.1f}..{high[1]:.1f} m)")
        print(f"{len(site_tracks)} rows mapped back with key {key.key_id} to {args.out}{spread}")
    return 0
