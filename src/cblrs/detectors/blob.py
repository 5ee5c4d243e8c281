"""A detector with no model: boxes around regions of one colour (tests, demos, markers)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import Detections
from cblrs.errors import CblrsError


class ColourBlobDetector:
    """Boxes around connected regions of one colour — a detector with no model.

    Useful for tests, demos and marker-based setups (e.g. coloured hats seen from above).

    Args:
        colour_rgb: the colour to find, (R, G, B) 0..255.
        tolerance: maximum absolute difference per channel.
        min_area: smallest region in pixels.
        class_id: class given to every box.
    """

    def __init__(
        self,
        colour_rgb: tuple[int, int, int],
        tolerance: int = 30,
        min_area: int = 20,
        class_id: int = 0,
    ):
        if len(colour_rgb) != 3 or not all(0 <= int(value) <= 255 for value in colour_rgb):
            raise CblrsError(f"blob colour must be three values 0..255, got {colour_rgb}.")
        self.colour_bgr = np.array(colour_rgb[::-1], dtype=np.int16)
        self.tolerance = int(tolerance)
        self.min_area = int(min_area)
        self.class_id = int(class_id)

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Boxes ``(x, y, x + w, y + h)`` of each region of at least ``min_area`` pixels."""
        # lazy: OpenCV takes ~80 ms to import; only this path needs it
        import cv2

        if image.ndim != 3 or image.shape[2] != 3:
            raise CblrsError(f"expected an (H, W, 3) image, got shape {image.shape}.")
        difference = np.abs(image.astype(np.int16) - self.colour_bgr).max(axis=2)
        mask = (difference <= self.tolerance).astype(np.uint8)
        count, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        stats = stats[1:count]
        stats = stats[stats[:, cv2.CC_STAT_AREA] >= self.min_area]
        x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
        width, height = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
        xyxy = np.column_stack([x, y, x + width, y + height]).astype(np.float64).reshape(-1, 4)
        order = np.lexsort((xyxy[:, 1], xyxy[:, 0]))
        return Detections(
            xyxy=xyxy[order],
            confidence=np.ones(len(xyxy)),
            class_id=np.full(len(xyxy), self.class_id, np.int64),
        )
