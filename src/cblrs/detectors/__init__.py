"""The detect stage: images -> boxes, on the camera.

* :class:`OnnxDetector` — YOLOX and Ultralytics YOLOv5/v8/v11 ONNX exports on the CPU
  (onnxruntime); users bring their own model file.
* :class:`TiledDetector` with :func:`plan_tiles` — the same detector on crops chosen from
  the camera's reference image, so that far, small people are seen at native resolution.
* :class:`YoloDetector` — Ultralytics through torch (extra ``cblrs[yolo]``).
* :class:`ColourBlobDetector` — boxes around regions of one colour, no model.

Every detector has ``detect(image) -> Detections`` (:class:`Detector`); boxes are image
pixels, classes those of :data:`cblrs.detections.CLASS_NAMES`.
"""

from __future__ import annotations

from pathlib import Path

from cblrs.detectors.base import (
    COCO_CLASS_NAMES,
    Detector,
    box_cover,
    box_iou,
    class_map,
    non_maximum_suppression,
)
from cblrs.detectors.blob import ColourBlobDetector
from cblrs.detectors.onnx import (
    DEFAULT_CONFIDENCE,
    DEFAULT_IOU,
    LAYOUTS,
    ModelError,
    OnnxDetector,
    letterbox,
)
from cblrs.detectors.tiling import (
    DEFAULT_MIN_OBJECT_PX,
    Tile,
    TiledDetector,
    TilePlan,
    plan_tiles,
    whole_frame_plan,
)
from cblrs.detectors.ultralytics_yolo import YoloDetector
from cblrs.reference import Reference

TILING_MODES = ("auto", "off")
"""``auto``: tiles from the reference image (:func:`plan_tiles`); ``off``: the whole frame."""
DEFAULT_TILING = "auto"

__all__ = [
    "COCO_CLASS_NAMES",
    "DEFAULT_CONFIDENCE",
    "DEFAULT_IOU",
    "DEFAULT_MIN_OBJECT_PX",
    "DEFAULT_TILING",
    "LAYOUTS",
    "TILING_MODES",
    "ColourBlobDetector",
    "Detector",
    "ModelError",
    "OnnxDetector",
    "Tile",
    "TilePlan",
    "TiledDetector",
    "YoloDetector",
    "box_cover",
    "box_iou",
    "class_map",
    "letterbox",
    "non_maximum_suppression",
    "onnx_camera_detector",
    "plan_tiles",
    "whole_frame_plan",
]


def onnx_camera_detector(
    model: str | Path | OnnxDetector,
    reference: Reference | None = None,
    tiling: str = DEFAULT_TILING,
    confidence: float = DEFAULT_CONFIDENCE,
    iou: float = DEFAULT_IOU,
    layout: str = "auto",
) -> TiledDetector:
    """An ONNX detector for one camera, tiled from its reference image.

    Args:
        model: the ``.onnx`` file, or a loaded :class:`OnnxDetector` (shared by cameras).
        reference: the camera's reference image; needed for ``tiling="auto"``.
        tiling: ``"auto"`` (tiles where the plane needs them) or ``"off"`` (whole frame).
        confidence, iou, layout: see :class:`OnnxDetector` (ignored for a loaded detector).

    Returns:
        A detector whose ``plan`` says which crops it runs.

    Raises:
        ModelError: an unusable model file.
        ValueError: an unknown tiling mode, or ``"auto"`` without a reference.
    """
    if tiling not in TILING_MODES:
        raise ValueError(f"tiling must be one of {', '.join(TILING_MODES)}, got {tiling!r}")
    detector = (
        model
        if isinstance(model, OnnxDetector)
        else OnnxDetector(model, confidence=confidence, iou=iou, layout=layout)
    )
    if reference is None:
        if tiling == "auto":
            raise ValueError("tiling 'auto' needs the camera's reference image")
        raise ValueError("the frame size comes from the reference image; give one")
    if tiling == "auto":
        plan = plan_tiles(reference, detector.input_size)
    else:
        plan = whole_frame_plan(reference.image_size, detector.input_size)
    return TiledDetector(detector, plan)
