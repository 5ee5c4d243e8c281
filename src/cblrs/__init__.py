"""cblrs: privacy-preserving multi-camera localisation with a Color Based Location Reference System.

The pipeline, one module per stage:
    calibration / camera -> plane -> reference -> targeting -> locate -> (send) ->
    matching -> evaluation / viz
"""

from __future__ import annotations

from cblrs.calibration import read_cameras, read_wildtrack_cameras
from cblrs.camera import Camera
from cblrs.detections import CLASS_NAMES, CameraMessage, Detections, Tracks
from cblrs.errors import (
    CalibrationError,
    CblrsError,
    DatasetError,
    PlaneError,
    ReferenceImageError,
)
from cblrs.locate import ColorLocator, HomographyLocator, Locator, LUTLocator
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import ReferenceImage, render_reference
from cblrs.targeting import TargetingPosition, target_pixels, targeting_for

__version__ = "0.1.0"

__all__ = [
    "CLASS_NAMES",
    "CalibrationError",
    "Camera",
    "CameraMessage",
    "CblrsError",
    "ColorLocator",
    "DatasetError",
    "Detections",
    "HomographyLocator",
    "LUTLocator",
    "Locator",
    "PlaneError",
    "PlaneSet",
    "PlaneSpec",
    "ReferenceImage",
    "ReferenceImageError",
    "TargetingPosition",
    "Tracks",
    "__version__",
    "read_cameras",
    "read_wildtrack_cameras",
    "render_reference",
    "target_pixels",
    "targeting_for",
]
