"""Ultralytics YOLO through its own Python package (torch), optional extra ``cblrs[yolo]``.

The ONNX adapter (:class:`cblrs.detectors.onnx.OnnxDetector`) runs the same models exported
with ``yolo export format=onnx`` without torch; this one takes ``.pt`` weights directly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CLASS_NAMES, Detections
from cblrs.errors import CblrsError


class YoloDetector:
    """Ultralytics YOLO with local weights (``pip install cblrs[yolo]``).

    Nothing is downloaded: ``weights`` must be an existing file (a ``.pt`` or exported model).
    Classes not in :data:`cblrs.detections.CLASS_NAMES` are dropped.

    Args:
        weights: path of the model file.
        confidence: minimum score.
        device: ``"cpu"``, ``"0"``, ... passed to Ultralytics.

    Raises:
        ImportError: ultralytics is not installed.
        CblrsError: the weights file does not exist.
    """

    def __init__(self, weights: str | Path, confidence: float = 0.25, device: str = "cpu"):
        weights = Path(weights)
        if not weights.is_file():
            raise CblrsError(
                f"YOLO weights {weights} do not exist; give a local model file with --weights "
                "(nothing is downloaded at run time)."
            )
        try:
            # optional extra: pip install cblrs[yolo]
            from ultralytics import YOLO
        except ImportError:
            raise ImportError(
                "the YOLO detector needs ultralytics: pip install cblrs[yolo]"
            ) from None
        self._model = YOLO(str(weights))
        self.confidence = float(confidence)
        self.device = device

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        results = self._model.predict(
            image, conf=self.confidence, device=self.device, verbose=False
        )
        return detections_from_ultralytics(results[0])


def detections_from_ultralytics(result: Any) -> Detections:
    """Map one ``ultralytics.engine.results.Results`` to :class:`Detections`.

    Uses ``result.names`` (class index -> name) and ``result.boxes.xyxy`` / ``.conf`` /
    ``.cls`` (torch tensors or arrays). Boxes whose class name is not in
    :data:`CLASS_NAMES` (the COCO names person, car, bicycle, motorcycle, bus, truck) are
    dropped.
    """
    boxes = result.boxes
    if boxes is None:
        return Detections.empty()
    xyxy = _to_numpy(boxes.xyxy).astype(np.float64).reshape(-1, 4)
    confidence = _to_numpy(boxes.conf).astype(np.float64).reshape(-1)
    model_class = _to_numpy(boxes.cls).astype(np.int64).reshape(-1)
    names = result.names
    class_id = np.array(
        [
            CLASS_NAMES.index(names[value]) if names.get(value) in CLASS_NAMES else -1
            for value in model_class.tolist()
        ],
        dtype=np.int64,
    )
    keep = class_id >= 0
    return Detections(xyxy=xyxy[keep], confidence=confidence[keep], class_id=class_id[keep])


def _to_numpy(value: Any) -> NDArray:
    if hasattr(value, "detach"):
        value = value.detach()
    if hasattr(value, "cpu"):
        value = value.cpu()
    if hasattr(value, "numpy"):
        value = value.numpy()
    return np.asarray(value)
