"""``cblrs calibrate``: clicked image <-> world points -> a camera, its errors and a picture."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.cli.common import (
    InputError,
    UsageError,
    add_output_options,
    format_table,
    print_json,
)


def register(subparsers) -> None:
    """Add the ``cblrs calibrate`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate a camera from clicked image <-> world points (CSV u,v,x,y)",
        description=(
            "Fit a camera to at least 4 clicked correspondences (CSV rows u,v,x,y[,name]; pixel "
            "u,v in the camera's frame, ground x,y in metres or site-map pixels): a ground "
            "homography from 4 points, the pose with a given focal length (--focal) from 4, the "
            "focal length too from 6 and lens distortion k1 from 8. Every model is fitted under "
            "the stated click and ground noise (--click-px, --ground-m), outliers are looked for "
            "from 5 points, and auto keeps the model that best predicts points left out of its "
            "fit. Prints each point's error in pixels and metres, writes the camera as cblrs "
            "camera JSON (--out) and a picture of the fit (--picture) that shades the part of "
            "the image the points leave poorly constrained."
        ),
    )
    parser.add_argument("points", type=Path, metavar="POINTS.csv", help="u,v,x,y[,name] rows")
    size = parser.add_mutually_exclusive_group(required=True)
    size.add_argument("--image", type=Path, help="a frame of the camera (gives the image size)")
    size.add_argument("--image-size", metavar="WIDTHxHEIGHT", help="the image size, e.g. 1920x1080")
    parser.add_argument("--name", help="camera name (default: the points file's stem)")
    parser.add_argument("--focal", type=float, metavar="PX", help="focal length guess, pixels")
    parser.add_argument(
        "--model",
        choices=("auto", "homography", "pose", "focal", "k1"),
        default="auto",
        help="what to fit (default auto: the model that best predicts held-out points)",
    )
    noise = parser.add_argument_group("how exact the points are (one standard deviation)")
    noise.add_argument("--click-px", type=float, default=2.0, help="of a click, pixels (default 2)")
    noise.add_argument(
        "--ground-m",
        type=float,
        default=0.1,
        help="of a point's ground position (the site plan's accuracy), metres (default 0.1)",
    )
    world = parser.add_argument_group("world coordinates")
    world.add_argument(
        "--world",
        choices=("metres", "map"),
        default="metres",
        help="x,y are metres (default) or pixels of the site map",
    )
    world.add_argument("--site", type=Path, help="site file whose map converts map pixels")
    world.add_argument("--metres-per-pixel", type=float, help="the map's scale")
    world.add_argument(
        "--map-origin", metavar="U,V", default="0,0", help="map pixel of the world origin"
    )
    world.add_argument(
        "--map-y-down", action="store_true", help="world y grows down the map (default: up)"
    )
    plausible = parser.add_argument_group("what a plausible camera is")
    plausible.add_argument(
        "--left-handed",
        action="store_true",
        help="the world's axes are left-handed (seen from above, x turns clockwise onto y); "
        "otherwise mirrored points (u,v or x,y swapped) are refused",
    )
    plausible.add_argument(
        "--max-height-m",
        type=float,
        default=100.0,
        help="refuse a fit that puts the camera higher (ground positions in centimetres?), "
        "metres (default 100)",
    )
    parser.add_argument(
        "--ransac-px",
        type=float,
        help="an outlier threshold in pixels instead of the test under the stated noise",
    )
    parser.add_argument("--out", type=Path, help="write the camera (cblrs camera JSON)")
    parser.add_argument("--picture", type=Path, help="write the picture of the fit (PNG)")
    parser.add_argument("--grid", type=float, metavar="M", help="grid spacing of the picture")
    add_output_options(parser)
    parser.set_defaults(handler=run)


def _image_size(args: argparse.Namespace) -> tuple[tuple[int, int], np.ndarray | None]:
    if args.image is not None:
        # lazy: OpenCV takes ~80 ms to import; only this path needs it
        import cv2

        if not args.image.is_file():
            raise InputError(f"--image {args.image} does not exist.")
        frame = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
        if frame is None:
            raise UsageError(f"--image {args.image} is not an image OpenCV can read.")
        return (frame.shape[1], frame.shape[0]), frame[..., ::-1].copy()
    text = args.image_size.lower().replace(",", "x")
    try:
        width, height = (int(value) for value in text.split("x"))
    except ValueError:
        raise UsageError(f"--image-size {args.image_size!r} must be WIDTHxHEIGHT.") from None
    if width <= 0 or height <= 0:
        raise UsageError(f"--image-size {args.image_size!r} must be positive.")
    return (width, height), None


def _world_transform(args: argparse.Namespace) -> Any:
    if args.world == "metres":
        if args.site is not None or args.metres_per_pixel is not None:
            raise UsageError("--site and --metres-per-pixel are for --world map.")
        return None
    if args.site is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.site import load_site

        site = load_site(args.site)
        if site.map is None:
            raise UsageError(
                f"{args.site.name} has no map, so map pixels cannot become metres "
                "(map: {metres_per_pixel: ...})."
            )
        return site.map.to_world
    if args.metres_per_pixel is None:
        raise UsageError(
            "--world map needs the map's scale: --metres-per-pixel S or --site with a map."
        )
    if not (math.isfinite(args.metres_per_pixel) and args.metres_per_pixel > 0):
        raise UsageError("--metres-per-pixel must be a positive number.")
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site import SiteMap

    try:
        u, v = (float(value) for value in args.map_origin.split(","))
    except ValueError:
        raise UsageError(f"--map-origin {args.map_origin!r} must be U,V map pixels.") from None
    return SiteMap(args.metres_per_pixel, (u, v), not args.map_y_down).to_world


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs calibrate`` with its parsed arguments; the exit code."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.calibrate import Correspondences, calibrate_camera

    image_size, frame = _image_size(args)
    transform = _world_transform(args)
    points = Correspondences.from_csv(args.points, transform)
    name = args.name or args.points.stem
    fit = calibrate_camera(
        points,
        image_size,
        name,
        focal_px=args.focal,
        model=args.model,
        ransac_px=args.ransac_px,
        click_px=args.click_px,
        ground_m=args.ground_m,
        left_handed=args.left_handed,
        max_height_m=args.max_height_m,
    )
    summary = fit.to_dict()
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary["camera"], indent=2) + "\n")
        summary["out"] = str(args.out)
    if args.picture is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.viz.calibration import calibration_picture
        from cblrs.viz.overlay import save_image

        if args.picture.suffix.lower() != ".png":
            raise UsageError(f"--picture {args.picture} must be a .png file.")
        save_image(args.picture, calibration_picture(fit, frame, args.grid))
        summary["picture"] = str(args.picture)
    if args.json:
        print_json(summary)
        return 0
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.viz.calibration import summary_lines

    rows = [
        [
            point["name"],
            f"{point['u']:.1f}, {point['v']:.1f}",
            f"{point['x']:.2f}, {point['y']:.2f}",
            f"{point['error_px']:.1f}",
            "-" if point["error_m"] is None else f"{point['error_m']:.3f}",
            "" if point["inlier"] else "outlier",
        ]
        for point in summary["per_point"]
    ]
    print(format_table(["point", "u, v px", "x, y m", "error px", "error m", ""], rows))
    for line in summary_lines(fit):
        print(line)
    for warning in fit.warnings:
        print(f"warning: {warning}")
    for key in ("out", "picture"):
        if key in summary:
            print(f"wrote {summary[key]}")
    return 0
