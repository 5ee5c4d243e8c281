"""Dataset readers and generators; each produces a :class:`cblrs.datasets.scene.Scene`.

* :func:`load_scene` reads a WILDTRACK or MultiviewX folder;
* :func:`simulate_detections` degrades a scene's boxes like a real detector;
* :func:`read_tracks` / :func:`write_tracks` handle the AI City 2024 text format (and
  :func:`read_track_metadata` its sidecar with classes and frame rate).
"""

from cblrs.datasets.aicity import (
    TrackMetadata,
    apply_track_metadata,
    read_track_metadata,
    read_tracks,
    write_tracks,
)
from cblrs.datasets.multiview import detect_layout, load_scene
from cblrs.datasets.scene import Scene
from cblrs.datasets.simulate import simulate_detections

__all__ = [
    "Scene",
    "TrackMetadata",
    "apply_track_metadata",
    "detect_layout",
    "load_scene",
    "read_track_metadata",
    "read_tracks",
    "simulate_detections",
    "write_tracks",
]
