"""cblrs: privacy-preserving multi-camera localisation with a Color Based Location Reference System.

The pipeline, one module per stage:
    calibration / camera -> plane -> reference -> targeting -> locate -> (send) ->
    matching -> evaluation / viz
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# The names below are imported on first use (PEP 562): `import cblrs` and the command line's
# start-up (`cblrs --help`) do not pay for scipy, OpenCV and onnxruntime until a name that
# needs them is used. Type checkers and IDEs read the plain imports under TYPE_CHECKING.
_LAZY = {
    "CLASS_NAMES": "cblrs.detections",
    "CalibrationError": "cblrs.errors",
    "Camera": "cblrs.camera",
    "CameraMessage": "cblrs.detections",
    "CblrsError": "cblrs.errors",
    "ColorLocator": "cblrs.locate",
    "DatasetError": "cblrs.errors",
    "Detections": "cblrs.detections",
    "GeometricTargeter": "cblrs.geometric_targeting",
    "HomographyLocator": "cblrs.locate",
    "LUTLocator": "cblrs.locate",
    "Locator": "cblrs.locate",
    "Metrics": "cblrs.evaluation",
    "OnnxDetector": "cblrs.detectors",
    "PlaneError": "cblrs.errors",
    "PlaneSet": "cblrs.plane",
    "PlaneSpec": "cblrs.plane",
    "ReferenceImage": "cblrs.reference",
    "ReferenceImageError": "cblrs.errors",
    "Scene": "cblrs.datasets",
    "TargetingPosition": "cblrs.targeting",
    "TiledDetector": "cblrs.detectors",
    "TrackingResult": "cblrs.pipeline",
    "Tracks": "cblrs.detections",
    "evaluate": "cblrs.evaluation",
    "load_reference": "cblrs.reference",
    "load_scene": "cblrs.datasets",
    "make_matcher": "cblrs.matching",
    "make_message": "cblrs.edge",
    "plan_tiles": "cblrs.detectors",
    "read_aicity_calibration": "cblrs.calibration",
    "read_camera_json": "cblrs.calibration",
    "read_cameras": "cblrs.calibration",
    "read_tracks": "cblrs.datasets",
    "read_wildtrack_cameras": "cblrs.calibration",
    "render_reference": "cblrs.reference",
    "render_scene_references": "cblrs.pipeline",
    "simulate_detections": "cblrs.datasets",
    "target_pixels": "cblrs.targeting",
    "targeting_for": "cblrs.targeting",
    "track_scene": "cblrs.pipeline",
    "write_tracks": "cblrs.datasets",
}

if TYPE_CHECKING:
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
    from cblrs.reference import ReferenceImage, load_reference, render_reference
    from cblrs.targeting import TargetingPosition, target_pixels, targeting_for


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'cblrs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

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
    "load_reference",
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
