"""``cblrs show``: a reference image made visible, with a metric grid, as PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from cblrs.cli.common import InputError, UsageError, add_output_options, print_json
from cblrs.reference import ReferenceImage
from cblrs.viz.overlay import save_image
from cblrs.viz.reference import reference_overlay


def register(subparsers) -> None:
    """Add the ``cblrs show`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "show",
        help="visualise a reference image with a metric grid",
        description=(
            "Write a PNG showing the reference image (R, G stretched to 8 bits) and a "
            "labelled grid of world x/y lines, over a camera frame when one is given."
        ),
    )
    parser.add_argument("reference", type=Path, metavar="REFERENCE.png")
    parser.add_argument("--out", required=True, type=Path, metavar="OUT.png")
    parser.add_argument("--frame", type=Path, metavar="IMAGE", help="camera frame to draw over")
    parser.add_argument(
        "--grid",
        type=float,
        default=1.0,
        metavar="METRES",
        help="grid spacing in metres (0: no grid)",
    )
    parser.add_argument(
        "--alpha",
        type=float,
        default=None,
        help="weight of the reference colours over the frame (default 0.45)",
    )
    add_output_options(parser)
    parser.set_defaults(handler=run)


def read_frame(path: Path) -> np.ndarray:
    """A frame as (H, W, 3) uint8 RGB."""
    if not path.is_file():
        raise InputError(f"frame {path} does not exist.")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise UsageError(f"frame {path} is not an image OpenCV can read.")
    return np.ascontiguousarray(image[..., ::-1])


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs show`` with its parsed arguments; the exit code."""
    if args.grid < 0 or not np.isfinite(args.grid):
        raise UsageError(f"--grid must be a non-negative number of metres, got {args.grid}.")
    if args.alpha is not None and not 0.0 <= args.alpha <= 1.0:
        raise UsageError(f"--alpha must be within 0..1, got {args.alpha}.")
    if args.out.suffix.lower() != ".png":
        raise UsageError(f"--out must be a .png file, got {args.out}.")
    reference = ReferenceImage.load(args.reference)
    frame = None
    if args.frame is not None:
        frame = read_frame(args.frame)
        width, height = reference.image_size
        if frame.shape[:2] != (height, width):
            raise UsageError(
                f"frame {args.frame} is {frame.shape[1]}x{frame.shape[0]} but the reference "
                f"is {width}x{height}."
            )
    image = reference_overlay(reference, frame, grid_m=args.grid or None, alpha=args.alpha)
    try:  # 0600: over a frame, the picture shows people
        save_image(args.out, image)
    except OSError as error:
        raise UsageError(f"could not write {args.out}: {error}") from None
    if args.json:
        print_json(
            {
                "out": str(args.out),
                "reference": str(args.reference),
                "camera": reference.camera_name,
                "image_size": list(reference.image_size),
                "coverage": reference.coverage(),
                "grid_m": args.grid,
                "frame": str(args.frame) if args.frame else None,
            }
        )
    elif not args.quiet:
        print(f"wrote {args.out}")
    return 0
