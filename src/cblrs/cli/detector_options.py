"""Options shared by ``cblrs track`` and ``cblrs demo`` for a data set's real detections:
a detector run on its images (``--detector onnx --model``) or a folder of detection files
(``--detections``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cblrs.cli.common import UsageError

# cblrs.detectors' own defaults, written out: importing the package (every detector module,
# ~10 ms) at the start of every `cblrs track` that tracks annotated boxes would cost more than
# the rest of its command line. tests/cli/test_cli_detector_options.py keeps them equal.
DEFAULT_CONFIDENCE = 0.25
DEFAULT_IOU = 0.45
DEFAULT_TILING = "auto"
LAYOUTS = ("auto", "yolox", "yolov5", "yolov8")
TILING_MODES = ("auto", "off")

DETECTIONS_HELP = (
    "folder of per-camera MOT files instead of the annotated boxes: one file per camera named "
    "after it (<camera>.txt, e.g. Camera1.txt or CVLab1.txt, or C1.txt after its image "
    "folder), lines frame,id,x,y,w,h,conf[,...] in pixels, frame numbers those of the "
    "dataset's annotation files (annotations_positions/<frame>.json; in the MultiviewX "
    "release in ../shared image NNNN.jpg is frame NNNN+1)"
)


def add_detector_options(parser, detections_help: str | None = None) -> None:
    """``--detector onnx --model``, tiling, thresholds (and ``--detections``) for datasets."""
    group = parser.add_argument_group("real detections (instead of the annotated boxes)")
    group.add_argument(
        "--detector",
        choices=("onnx",),
        help="run this detector on the dataset's images (Image_subsets/C<k>/)",
    )
    group.add_argument(
        "--model", type=Path, metavar="MODEL.onnx",
        help="ONNX model file: a YOLOX or Ultralytics YOLOv5/v8/v11 export (local; never "
        "downloaded)",
    )
    group.add_argument(
        "--tiling", choices=TILING_MODES, default=DEFAULT_TILING,
        help="auto: also detect on tiles where the reference image says people look small "
        "(default); off: the whole frame only",
    )
    group.add_argument(
        "--confidence", type=float, default=DEFAULT_CONFIDENCE,
        help=f"minimum detector score (default {DEFAULT_CONFIDENCE})",
    )
    group.add_argument(
        "--iou", type=float, default=DEFAULT_IOU,
        help=f"NMS IoU threshold (default {DEFAULT_IOU})",
    )
    group.add_argument(
        "--layout", choices=LAYOUTS, default="auto",
        help="model output layout (default: from its output shape)",
    )
    if detections_help is not None:
        group.add_argument("--detections", type=Path, metavar="DIR", help=detections_help)
    group.add_argument(
        "--hidden-feet", choices=("auto", "keep", "drop"), default="auto",
        help="boxes whose feet a nearer box hides: drop their location (default for a "
        "detector's boxes, which end where the person is hidden) or keep it (default for "
        "annotated boxes, which include hidden parts)",
    )


def detection_source(args: argparse.Namespace) -> str:
    """``"annotations"``, ``"detector"`` or ``"detections"``, after checking the options."""
    detections = getattr(args, "detections", None)
    if args.detector is not None and detections is not None:
        raise UsageError("give either --detector or --detections, not both.")
    if args.detector is not None:
        if args.model is None:
            raise UsageError(f"--detector {args.detector} needs --model MODEL.onnx.")
        if not 0.0 <= args.confidence <= 1.0:
            raise UsageError(f"--confidence must be within 0..1, got {args.confidence}.")
        if not 0.0 < args.iou <= 1.0:
            raise UsageError(f"--iou must be within (0, 1], got {args.iou}.")
        return "detector"
    if args.model is not None:
        raise UsageError("--model needs --detector onnx.")
    return "detections" if detections is not None else "annotations"


def drop_hidden_feet(args: argparse.Namespace, source: str) -> bool:
    """Whether boxes whose foot point the image cuts off are dropped: ``--hidden-feet``, or
    by default for real detections (annotated boxes keep theirs)."""
    if args.hidden_feet == "auto":
        return source != "annotations"
    return args.hidden_feet == "drop"


def real_detections(
    args: argparse.Namespace, scene: Any, references: Any, source: str, quiet: bool
) -> tuple[Any, dict[str, Any] | None]:
    """``(scene with the chosen detections, detector summary or None)``."""
    if source == "annotations":
        return scene, None
    if source == "detections":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.datasets.detection_folder import read_detection_folder

        scene = read_detection_folder(scene, args.detections, dataset_root=args.dataset)
        return scene, {"detections": str(args.detections)}
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.detectors.offline import detect_scene

    run = detect_scene(
        scene, args.dataset, args.model, references, tiling=args.tiling,
        confidence=args.confidence, iou=args.iou, layout=args.layout, progress=not quiet,
    )
    summary = {
        "model": str(args.model),
        "layout": run.layout,
        "tiling": args.tiling,
        "tiles": {camera.name: plan.describe() for camera, plan in zip(
            scene.cameras, run.plans, strict=True)},
        "images": run.images,
        "images_skipped": run.skipped,
        "detector_ms_per_image": round(run.ms_per_image, 2),
        "decode_ms_per_image": round(1000 * run.decode_seconds / max(run.images, 1), 2),
    }
    return run.scene, summary
