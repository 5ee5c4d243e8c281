"""The camera side of the pipeline: detections -> target pixels -> colours -> message.

This is all an edge camera computes per frame. Its output, a :class:`CameraMessage`, holds
boxes and reference colours only.
"""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage, Detections
from cblrs.reference import ReferenceImage
from cblrs.targeting import TargetingPosition, target_pixels, targeting_for


def targeting_columns(
    class_id: np.ndarray, overrides: dict[str, TargetingPosition] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-detection (horizontal, vertical) targeting fractions from class defaults."""
    overrides = overrides or {}
    horizontal = np.empty(len(class_id))
    vertical = np.empty(len(class_id))
    for value in np.unique(class_id):
        name = CLASS_NAMES[value] if 0 <= value < len(CLASS_NAMES) else "unknown"
        position = overrides.get(name, targeting_for(name))
        rows = class_id == value
        horizontal[rows] = position.horizontal
        vertical[rows] = position.vertical
    return horizontal, vertical


def make_message(
    camera_id: str,
    sequence: int,
    timestamp: float,
    frame: int,
    detections: Detections,
    reference: ReferenceImage,
    targeting: dict[str, TargetingPosition] | None = None,
) -> CameraMessage:
    """Localise one frame's detections through the reference image and build the message.

    Args:
        camera_id: the camera's name.
        sequence: per-camera message counter.
        timestamp: capture time, seconds.
        frame: frame number.
        detections: the frame's boxes.
        reference: the camera's reference image.
        targeting: per-class targeting overrides (defaults: :data:`DEFAULT_TARGETING`).

    Returns:
        The message; a detection whose target pixel sees no plane (or lies outside the
        image) carries colour (0, 0, 0).
    """
    horizontal, vertical = targeting_columns(detections.class_id, targeting)
    pixels, inside = target_pixels(
        detections.xyxy, horizontal, vertical, image_size=reference.image_size
    )
    colours, valid = reference.colours_at(pixels)
    colours[~(valid & inside)] = 0
    return CameraMessage(
        camera_id=camera_id,
        sequence=sequence,
        timestamp=timestamp,
        frame=frame,
        xyxy=detections.xyxy,
        confidence=detections.confidence,
        class_id=detections.class_id,
        colour=colours,
    )
