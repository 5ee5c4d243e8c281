"""Box -> target pixel (the paper's section III-B).

A detection box does not show where an object stands. The target pixel is picked at a
horizontal fraction of the box width and a vertical targeting position (VTP) measured from
the box top (0.5 = centre, 1.0 = bottom edge). The paper sweeps VTP from 50 % to 95 %.
For people the foot point (bottom centre) is the natural target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class TargetingPosition:
    """Where in a box to look: fractions of width (from the left) and height (from the top)."""

    horizontal: float = 0.5
    vertical: float = 1.0

    def __post_init__(self) -> None:
        for name in ("horizontal", "vertical"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} targeting position must be within 0..1, got {value}")


# Defaults per class. People: the foot point. Vehicles: the bottom edge lies between camera
# and vehicle (the paper's Fig. 1), so aim a little higher.
DEFAULT_TARGETING: dict[str, TargetingPosition] = {
    "person": TargetingPosition(0.5, 1.0),
    "car": TargetingPosition(0.5, 0.85),
    "truck": TargetingPosition(0.5, 0.85),
    "bus": TargetingPosition(0.5, 0.85),
    "bicycle": TargetingPosition(0.5, 0.95),
    "motorcycle": TargetingPosition(0.5, 0.95),
}
FALLBACK_TARGETING = TargetingPosition(0.5, 1.0)


def targeting_for(class_name: str) -> TargetingPosition:
    """Default targeting position of a class (foot point for unknown classes)."""
    return DEFAULT_TARGETING.get(class_name, FALLBACK_TARGETING)


def target_pixels(
    xyxy: NDArray,
    horizontal: float | NDArray = 0.5,
    vertical: float | NDArray = 1.0,
    image_size: tuple[int, int] | None = None,
) -> tuple[FloatArray, BoolArray]:
    """Target pixels of boxes.

    Args:
        xyxy: (N, 4) boxes in pixels (x_min, y_min, x_max, y_max).
        horizontal: fraction of the width from the left, scalar or (N,).
        vertical: VTP, fraction of the height from the top, scalar or (N,).
        image_size: (width, height). When given, targets outside the image (a box cut by the
            image border) are clamped to the nearest pixel inside it and flagged.

    Returns:
        ``(pixels, inside)``: (N, 2) float pixel coordinates and (N,) bool, False where the
        target had to be clamped (its location is then only a bound) or the box is invalid.

    Example:
        >>> target_pixels([[100, 50, 140, 250]])[0].tolist()
        [[120.0, 250.0]]
    """
    boxes = np.asarray(xyxy, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"xyxy must have shape (N, 4), got {boxes.shape}")
    horizontal = np.asarray(horizontal, dtype=np.float64)
    vertical = np.asarray(vertical, dtype=np.float64)
    pixels = np.column_stack(
        [
            boxes[:, 0] + horizontal * (boxes[:, 2] - boxes[:, 0]),
            boxes[:, 1] + vertical * (boxes[:, 3] - boxes[:, 1]),
        ]
    )
    with np.errstate(invalid="ignore"):
        inside = (
            np.isfinite(boxes).all(axis=1)
            & (boxes[:, 2] >= boxes[:, 0])
            & (boxes[:, 3] >= boxes[:, 1])
        )
    if image_size is not None:
        width, height = image_size
        # The last pixel centre is size - 1; a box edge at x_max = width is still in view.
        limit = np.array([width - 1.0, height - 1.0])
        with np.errstate(invalid="ignore"):
            outside = ((pixels < 0) | (pixels > limit + 1.0)).any(axis=1)
        inside &= ~outside
        pixels = np.clip(pixels, 0.0, limit)
    return pixels, inside
