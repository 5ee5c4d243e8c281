"""``cblrs render``: calibration -> one colour reference PNG per camera."""

from __future__ import annotations

import argparse
import json
import re
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2

from cblrs.calibration import default_ground, read_cameras
from cblrs.cli.common import (
    InputError,
    UsageError,
    add_output_options,
    format_table,
    print_json,
    progress,
)
from cblrs.errors import PlaneError
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference


def register(subparsers) -> None:
    """Add the ``cblrs render`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "render",
        help="render colour reference images from a calibration",
        description=(
            "Render one colour reference PNG per camera, from a data set (--dataset, a "
            "WILDTRACK or MultiviewX folder), a site file (--site) or CALIBRATION: an AI City "
            "calibration.json (or a folder of them), a cblrs camera JSON file or a data set "
            "folder."
        ),
    )
    parser.add_argument(
        "calibration", metavar="CALIBRATION", nargs="?", help="calibration file or folder"
    )
    parser.add_argument(
        "--dataset", type=Path, metavar="PATH",
        help="a WILDTRACK or MultiviewX folder: its cameras and ground (as CALIBRATION)",
    )
    parser.add_argument(
        "--site", type=Path, help="a site file: its cameras and planes (instead of CALIBRATION)"
    )
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument(
        "--bits", type=int, choices=(8, 16), default=None, help="bits per channel (default 16)"
    )
    parser.add_argument(
        "--plane",
        action="append",
        default=[],
        metavar="X0,Y0,WIDTH,LENGTH[,HEIGHT]",
        help="a plane in metres (repeatable; ids 1, 2, ...); default: the dataset's ground area",
    )
    parser.add_argument("--planes-file", type=Path, help="JSON list of plane specifications")
    parser.add_argument(
        "--distorted",
        action="store_true",
        help="use the lens-distortion calibration (WILDTRACK intrinsic_original) for raw video",
    )
    parser.add_argument(
        "--preview", action="store_true", help="also write <camera>_preview.png with a 1 m grid"
    )
    parser.add_argument(
        "--key", type=Path, help="pseudo-coordinate key (cblrs pseudo keygen): the colours "
        "encode the key's pseudo frame, not the site's (see docs/privacy.md)"
    )
    add_output_options(parser)
    # Let `--plane -3,-9,12,36` through: argparse (before Python 3.13) takes any word that
    # starts with "-" and is not a plain negative number for an option.
    parser._negative_number_matcher = re.compile(r"^-\.?\d")
    parser.set_defaults(handler=run)


def parse_plane(text: str, plane_id: int, bits: int) -> PlaneSpec:
    """A plane from ``X0,Y0,WIDTH,LENGTH[,HEIGHT]`` (metres)."""
    try:
        values = [float(value) for value in text.split(",")]
    except ValueError:
        raise UsageError(f"--plane {text!r} must be numbers X0,Y0,WIDTH,LENGTH[,HEIGHT].") from None
    if len(values) not in (4, 5):
        raise UsageError(
            f"--plane {text!r} needs 4 or 5 numbers (X0,Y0,WIDTH,LENGTH[,HEIGHT]), "
            f"got {len(values)}."
        )
    height = values[4] if len(values) == 5 else 0.0
    return PlaneSpec(plane_id, (values[0], values[1]), values[2], values[3], bits, height)


def read_planes_file(path: Path, bits: int | None) -> list[PlaneSpec]:
    """Planes from a JSON list (or ``{"planes": [...]}``) of plane specifications."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"planes file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise UsageError(f"planes file {path} is not valid JSON: {error}.") from None
    if isinstance(data, dict):
        data = data.get("planes")
    if not isinstance(data, list) or not all(isinstance(item, dict) for item in data):
        raise UsageError(f"planes file {path} must hold a list of plane objects.")
    try:
        planes = [PlaneSpec.from_dict(item) for item in data]
    except PlaneError as error:
        raise PlaneError(f"{path}: {error}") from None
    if bits is not None:
        planes = [replace(plane, bits=bits) for plane in planes]
    return planes


def build_planes(args: argparse.Namespace) -> PlaneSet:
    """The planes of ``--plane`` and ``--planes-file`` (or the data set's default ground)."""
    bits = args.bits or 16
    planes = [
        parse_plane(text, plane_id, bits) for plane_id, text in enumerate(args.plane, start=1)
    ]
    if args.planes_file is not None:
        extra = read_planes_file(args.planes_file, args.bits)
        if planes and extra and args.bits is None:
            extra = [replace(plane, bits=bits) for plane in extra]
        planes += extra
    if not planes:
        ground = default_ground(args.calibration)
        if ground is None:
            raise UsageError(
                f"{args.calibration} is not a WILDTRACK or MultiviewX folder, so give the "
                "plane extent with --plane X0,Y0,WIDTH,LENGTH or --planes-file."
            )
        # The same plane as `cblrs track` and the demo use (`load_scene`): the annotated area
        # grown by a margin, so that foot points of people at its border still decode.
        from cblrs.datasets.multiview import GROUND_MARGIN_M as margin

        x0, y0, width, length = ground
        planes = [
            PlaneSpec(
                1, (x0 - margin, y0 - margin), width + 2 * margin, length + 2 * margin, bits,
                name="ground",
            )
        ]
    return PlaneSet(planes)


def file_name(camera_name: str, index: int) -> str:
    """A safe file stem for a camera name."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", camera_name).strip("._")
    return stem or f"camera{index + 1}"


def site_cameras_and_planes(
    args: argparse.Namespace,
) -> tuple[list, list[PlaneSet], PlaneSet]:
    """The cameras of ``--site``, each one's planes (its own plane, or all) and all the site's
    planes (``--bits`` applied)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site import load_site

    if args.calibration is not None:
        raise UsageError("give --dataset (or CALIBRATION) or --site, not both.")
    if args.plane or args.planes_file is not None or args.distorted:
        raise UsageError(
            "--plane, --planes-file and --distorted do not go with --site: the site file gives "
            "the planes and each camera's calibration."
        )
    site = load_site(args.site)
    if site.pseudo_key_id is not None:
        raise UsageError(
            f"{args.site} is a pseudo site (key {site.pseudo_key_id}); render from the real "
            "site with --key: cblrs render --site SITE --key KEY --out DIR."
        )

    def with_bits(planes: PlaneSet) -> PlaneSet:
        if args.bits is not None and args.bits != planes.bits:
            return PlaneSet([replace(plane, bits=args.bits) for plane in planes])
        return planes

    all_planes = with_bits(site.require_planes("render"))
    cameras = site.require_cameras("render")
    per_camera = [with_bits(site.camera_planes(camera.name)) for camera in cameras]
    return [camera.camera for camera in cameras], per_camera, all_planes


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs render`` with its parsed arguments; the exit code."""
    if args.dataset is not None:
        # The data set's folder is spelled --dataset on every subcommand; CALIBRATION also
        # takes calibration files, so it stays.
        if args.calibration is not None and Path(args.calibration) != args.dataset:
            raise UsageError("CALIBRATION and --dataset name different folders; give one.")
        if not args.dataset.is_dir():
            raise InputError(f"--dataset {args.dataset} is not a folder.")
        args.calibration = str(args.dataset)
    if args.site is not None:
        cameras, camera_planes, all_planes = site_cameras_and_planes(args)
    elif args.calibration is None:
        raise UsageError("give --dataset DIR, a CALIBRATION file or folder, or --site SITE.")
    else:
        cameras = read_cameras(args.calibration, distorted=args.distorted)
        all_planes = build_planes(args)
        camera_planes = [all_planes] * len(cameras)
    key = None
    if args.key is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.privacy import PseudoKey, render_pseudo_reference

        key = PseudoKey.load(args.key)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for index, camera in enumerate(progress(cameras, "render", args.quiet)):
        start = time.perf_counter()
        planes = camera_planes[index]
        if key is None:
            reference = render_reference(camera, planes)
        else:
            reference = render_pseudo_reference(camera, planes, key)
        milliseconds = (time.perf_counter() - start) * 1000.0
        stem = file_name(camera.name, index)
        path = reference.save(args.out / f"{stem}.png")
        row: dict[str, Any] = {
            "camera": camera.name,
            "path": str(path),
            "coverage": reference.coverage(),
            "planes": planes.ids,
            "step_cm": [100.0 * step for step in reference.planes[0].step],
            "render_ms": milliseconds,
            "bytes": path.stat().st_size,
        }
        if args.preview:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.viz.reference import reference_overlay

            preview = reference_overlay(reference, None, grid_m=1.0)
            preview_path = args.out / f"{stem}_preview.png"
            if not cv2.imwrite(str(preview_path), preview[..., ::-1]):
                raise UsageError(f"could not write {preview_path}.")
            row["preview"] = str(preview_path)
        rows.append(row)
    if args.json:
        print_json(
            {
                "bits": all_planes.bits,
                "planes": (all_planes if key is None else key.pseudo_planes(all_planes)).to_list(),
                "pseudo_key_id": None if key is None else key.key_id,
                "distorted": args.distorted,
                "cameras": rows,
            }
        )
        return 0
    table = [
        [
            row["camera"],
            f"{100 * row['coverage']:.1f}",
            "x".join(f"{step:.3g}" for step in row["step_cm"]),
            f"{row['render_ms']:.0f}",
            _size(row["bytes"]),
        ]
        for row in rows
    ]
    print(format_table(["camera", "coverage %", "step cm", "ms", "file"], table))
    print(f"{len(rows)} reference image(s) in {args.out}"
          + ("" if key is None else f", colours in the pseudo frame of key {key.key_id}"))
    return 0


def _size(size: int) -> str:
    for unit in ("B", "kB", "MB"):
        if size < 1000 or unit == "MB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000  # type: ignore[assignment]
    return str(size)
