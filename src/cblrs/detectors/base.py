"""What every detector shares: the interface, COCO -> cblrs classes, non-maximum suppression."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CLASS_NAMES, Detections

COCO_CLASS_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat",
    "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack",
    "umbrella", "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball",
    "kite", "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket",
    "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair",
    "couch", "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse",
    "remote", "keyboard", "cell phone", "microwave", "oven", "toaster", "sink",
    "refrigerator", "book", "clock", "vase", "scissors", "teddy bear", "hair drier",
    "toothbrush",
)  # fmt: skip
"""The 80 COCO classes in the order YOLOX and Ultralytics models number them."""

# Model class names that mean a cblrs class (COCO's names, plus a few common spellings).
_ALIASES = {"motorbike": "motorcycle", "pedestrian": "person", "people": "person"}


@runtime_checkable
class Detector(Protocol):
    """Anything that turns an image into boxes."""

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Detect objects.

        Args:
            image: (H, W, 3) uint8 image in OpenCV's BGR channel order.

        Returns:
            The boxes in pixels, with class ids from :data:`cblrs.detections.CLASS_NAMES`.
        """
        ...


def class_map(model_names: list[str] | tuple[str, ...]) -> NDArray[np.int64]:
    """For each model class, the cblrs class id, or -1 for classes cblrs does not track.

    Args:
        model_names: the model's class names in its own order (e.g. :data:`COCO_CLASS_NAMES`).

    Returns:
        (C,) int64: person, car, bicycle, motorcycle, bus and truck map to their index in
        :data:`cblrs.detections.CLASS_NAMES`; everything else to -1.
    """
    mapping = np.full(len(model_names), -1, dtype=np.int64)
    for index, name in enumerate(model_names):
        name = _ALIASES.get(str(name).strip().lower(), str(name).strip().lower())
        if name in CLASS_NAMES:
            mapping[index] = CLASS_NAMES.index(name)
    return mapping


def non_maximum_suppression(
    xyxy: NDArray[np.float64],
    scores: NDArray[np.float64],
    class_id: NDArray[np.int64],
    iou_threshold: float,
) -> NDArray[np.int64]:
    """Indices of the boxes kept by class-aware greedy NMS, best score first.

    Args:
        xyxy: (N, 4) float64 boxes, pixels.
        scores: (N,) float64.
        class_id: (N,) int64; boxes of different classes never suppress each other.
        iou_threshold: a box is dropped when it overlaps a better one of its class by more.

    Returns:
        (K,) int64 row indices.
    """
    if len(xyxy) == 0:
        return np.zeros(0, dtype=np.int64)
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    boxes: Any = np.column_stack([xyxy[:, :2], xyxy[:, 2:] - xyxy[:, :2]]).astype(np.float64)
    confidences: Any = np.asarray(scores, dtype=np.float32)
    classes: Any = np.asarray(class_id, dtype=np.int32)
    result = cv2.dnn.NMSBoxesBatched(
        boxes,
        confidences,
        classes,
        score_threshold=float(np.min(scores)) - 1.0,
        nms_threshold=float(iou_threshold),
    )
    kept = np.asarray(result, dtype=np.int64).reshape(-1)
    return kept[np.argsort(-scores[kept], kind="stable")]


def box_iou(first: NDArray[np.float64], second: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, M) intersection over union of two sets of xyxy boxes."""
    return _overlap(first, second) / np.maximum(_union(first, second), 1e-12)


def box_cover(first: NDArray[np.float64], second: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, M) share of each ``first`` box's area that lies inside each ``second`` box."""
    area = np.maximum(first[:, 2] - first[:, 0], 0) * np.maximum(first[:, 3] - first[:, 1], 0)
    return _overlap(first, second) / np.maximum(area[:, None], 1e-12)


def _overlap(first: NDArray[np.float64], second: NDArray[np.float64]) -> NDArray[np.float64]:
    width = np.minimum(first[:, None, 2], second[None, :, 2]) - np.maximum(
        first[:, None, 0], second[None, :, 0]
    )
    height = np.minimum(first[:, None, 3], second[None, :, 3]) - np.maximum(
        first[:, None, 1], second[None, :, 1]
    )
    return np.maximum(width, 0) * np.maximum(height, 0)


def _union(first: NDArray[np.float64], second: NDArray[np.float64]) -> NDArray[np.float64]:
    def area(boxes: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.maximum(boxes[:, 2] - boxes[:, 0], 0) * np.maximum(boxes[:, 3] - boxes[:, 1], 0)

    return area(first)[:, None] + area(second)[None, :] - _overlap(first, second)
