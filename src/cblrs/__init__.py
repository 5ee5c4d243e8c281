"""cblrs: privacy-preserving multi-camera localisation with a Color Based Location Reference System.

The pipeline, one module per stage:
    calibration / camera -> plane -> reference -> targeting -> locate -> (send) ->
    matching -> evaluation / viz
"""

from __future__ import annotations

from cblrs.calibration import (
    read_aicity_calibration,
    read_camera_json,
    read_cameras,
    read_wildtrack_cameras,
)
from cblrs.camera import Camera
from cblrs.datasets import Scene, load_scene, read_tracks, simulate_detections, write_tracks
from cblrs.detections import CLASS_NAMES, CameraMessage, Detections, Tracks
from cblrs.detectors import OnnxDetector, TiledDetector, plan_tiles
from cblrs.edge import make_message
from cblrs.errors import (
    CalibrationError,
    CblrsError,
    DatasetError,
    PlaneError,
    ReferenceImageError,
)
from cblrs.evaluation import Metrics, evaluate
from cblrs.geometric_targeting import GeometricTargeter
from cblrs.locate import ColorLocator, HomographyLocator, Locator, LUTLocator
from cblrs.matching import make_matcher
from cblrs.pipeline import TrackingResult, render_scene_references, track_scene
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import ReferenceImage, render_reference
from cblrs.targeting import TargetingPosition, target_pixels, targeting_for

__version__ = "0.1.0"

# The runtime (MQTT services) lives in `cblrs.runtime`, the synthetic world in
# `cblrs.datasets.synthetic` and the pictures in `cblrs.viz` (matplotlib); import them from there.

__all__ = [
    "CLASS_NAMES",
    "CalibrationError",
    "Camera",
    "CameraMessage",
    "CblrsError",
    "ColorLocator",
    "DatasetError",
    "Detections",
    "GeometricTargeter",
    "HomographyLocator",
    "LUTLocator",
    "Locator",
    "Metrics",
    "OnnxDetector",
    "PlaneError",
    "PlaneSet",
    "PlaneSpec",
    "ReferenceImage",
    "ReferenceImageError",
    "Scene",
    "TargetingPosition",
    "TiledDetector",
    "TrackingResult",
    "Tracks",
    "__version__",
    "evaluate",
    "load_scene",
    "make_matcher",
    "make_message",
    "plan_tiles",
    "read_aicity_calibration",
    "read_camera_json",
    "read_cameras",
    "read_tracks",
    "read_wildtrack_cameras",
    "render_reference",
    "render_scene_references",
    "simulate_detections",
    "target_pixels",
    "targeting_for",
    "track_scene",
    "write_tracks",
]
