"""The detect stage over a whole data set: every camera's images through a detector.

:func:`detect_scene` turns a WILDTRACK / MultiviewX scene whose detections are its annotated
boxes into the same scene with a real detector's boxes instead, exactly as each camera
would produce them (one detector per camera, tiled from that camera's reference image).
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from cblrs.datasets.images import SkippedImages, UnusableImage, read_image, scene_image_paths
from cblrs.datasets.scene import Scene
from cblrs.detections import Detections
from cblrs.detectors import (
    DEFAULT_CONFIDENCE,
    DEFAULT_IOU,
    DEFAULT_TILING,
    OnnxDetector,
    TilePlan,
    onnx_camera_detector,
)
from cblrs.errors import DatasetError
from cblrs.reference import Reference

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class DetectionRun:
    """What :func:`detect_scene` produced.

    Attributes:
        scene: the input scene with the detector's boxes as detections (``object_id`` -1).
        layout: the model's output layout (``yolox``, ``yolov5``, ``yolov8``).
        plans: each camera's tile plan.
        images: images read and detected.
        decode_seconds: time spent reading and decoding image files.
        detect_seconds: time spent in the detector (tiles, inference, merging).
        skipped: images skipped because their file was unusable (empty, cut short,
            undecodable), by reason; their camera has no boxes at that frame.
    """

    scene: Scene
    layout: str
    plans: list[TilePlan]
    images: int
    decode_seconds: float
    detect_seconds: float
    skipped: dict[str, int] = field(default_factory=dict)

    @property
    def ms_per_image(self) -> float:
        """Mean detector time per camera frame, milliseconds."""
        return 1000.0 * self.detect_seconds / max(self.images, 1)


def detect_scene(
    scene: Scene,
    root: str | Path,
    model: str | Path | OnnxDetector,
    references: Sequence[Reference],
    tiling: str = DEFAULT_TILING,
    confidence: float = DEFAULT_CONFIDENCE,
    iou: float = DEFAULT_IOU,
    layout: str = "auto",
    progress: bool = False,
) -> DetectionRun:
    """Detect on a data set's images (``Image_subsets/C<k>/``) instead of its annotations.

    Args:
        scene: the scene loaded from ``root`` (its frames pick the images).
        root: the data set folder.
        model: the ONNX model file, or a loaded :class:`OnnxDetector`.
        references: each camera's reference image (tiles are planned from them).
        tiling: ``"auto"`` or ``"off"`` (see :func:`cblrs.detectors.onnx_camera_detector`).
        confidence, iou, layout: detector settings (see :class:`OnnxDetector`).
        progress: a progress bar on stderr (terminals only).

    Returns:
        The scene with detected boxes, the plans and timings.

    Raises:
        DatasetError: missing image folders or images, or an image whose size differs from
            the camera's (an empty, cut short or undecodable image is skipped and counted).
        ModelError: an unusable model.
    """
    detector = (
        model
        if isinstance(model, OnnxDetector)
        else OnnxDetector(model, confidence=confidence, iou=iou, layout=layout)
    )
    cameras = [
        onnx_camera_detector(detector, reference, tiling=tiling) for reference in references
    ]
    paths = scene_image_paths(root, len(scene.cameras), scene.frames)
    rows = enumerate(paths)
    if progress:

        rows = tqdm(rows, total=len(paths), desc="detecting", leave=False,
                    disable=not sys.stderr.isatty())
    detections: list[list[Detections]] = []
    decode_seconds = detect_seconds = 0.0
    skipped = SkippedImages(f"{root}")
    for _, frame_paths in rows:
        per_camera = []
        for camera, camera_detector, path in zip(scene.cameras, cameras, frame_paths, strict=True):
            started = time.perf_counter()
            try:
                image = read_image(path)
            except UnusableImage as error:
                # Skipped, counted and logged: the camera gives no boxes at this frame.
                skipped.skip(error)
                per_camera.append(Detections.empty())
                continue
            decoded = time.perf_counter()
            if (image.shape[1], image.shape[0]) != camera.image_size:
                raise DatasetError(
                    f"image {path} is {image.shape[1]}x{image.shape[0]} but camera "
                    f"{camera.name} is calibrated for {camera.image_size[0]}x"
                    f"{camera.image_size[1]}."
                )
            per_camera.append(camera_detector.detect(image))
            detect_seconds += time.perf_counter() - decoded
            decode_seconds += decoded - started
        detections.append(per_camera)
    if skipped.total and skipped.total == len(paths) * len(scene.cameras):
        raise DatasetError(
            f"every one of the {skipped.total} images of {root} is unusable ("
            + ", ".join(f"{count} {reason}" for reason, count in sorted(skipped.counts.items()))
            + ")."
        )
    logger.debug(
        "detected %d images: decode %.2f s, detector %.2f s",
        len(paths) * len(scene.cameras), decode_seconds, detect_seconds,
    )
    return DetectionRun(
        scene=replace(scene, detections=detections),
        layout=detector.layout,
        plans=[camera.plan for camera in cameras],
        images=len(paths) * len(scene.cameras) - skipped.total,
        decode_seconds=decode_seconds,
        detect_seconds=detect_seconds,
        skipped=dict(skipped.counts),
    )
