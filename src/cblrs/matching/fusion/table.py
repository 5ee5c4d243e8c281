"""The fusion tracker's state, as its stages see it: one row per track, numpy columns.

:class:`TrackTable` declares what :class:`~cblrs.matching.fusion.tracker.FusionTracker` holds
(set in its ``__init__`` and ``reset``), so that the stages written as its mixins
(:mod:`~cblrs.matching.fusion.association`, :mod:`~cblrs.matching.fusion.birth`,
:mod:`~cblrs.matching.fusion.clocks`, :mod:`~cblrs.matching.fusion.state`) can be read, and
type-checked, on their own. It also holds the two helpers every stage uses.
"""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.clock import ClockModel
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.timing import WindowBuffer


class TrackTable:
    """Declarations of the tracker's attributes (no values here) and the shared helpers."""

    config: FusionConfig
    camera_ids: list[str]
    # One row per track (tentative tracks have id -1).
    _ids: np.ndarray  # (T,) int64
    _class: np.ndarray  # (T,) int64 class ids
    _state: np.ndarray  # (T, 4) x, y, vx, vy (m, m/s), the models combined
    _covariance: np.ndarray  # (T, 4, 4)
    _mode_state: np.ndarray  # (T, M, 4) per motion model
    _mode_covariance: np.ndarray  # (T, M, 4, 4)
    _mode_probability: np.ndarray  # (T, M)
    _evidence: np.ndarray  # (T,) detections taken so far
    _last_seen: np.ndarray  # (T,) seconds
    _seen_by: np.ndarray  # (T, C) when each camera last saw the track (-inf: never)
    # Per camera and per class.
    _camera_xy: np.ndarray  # (C, 2) metres, NaN where not placed
    _class_extra: np.ndarray  # (K + 1,) extra measurement sigma of each class, metres
    _class_scale: np.ndarray  # (K + 1,) gate and cluster scale relative to a person
    # Per detection of the window being fused (set by the measurement step).
    _distance: np.ndarray
    _along_distance: np.ndarray
    _direction: np.ndarray
    _sigma: np.ndarray
    # Births of the window being fused (set by the birth step).
    _birth_cameras: np.ndarray
    _birth_camera: np.ndarray
    _birth_box: np.ndarray
    # Models and bookkeeping.
    _object_covariance: np.ndarray  # (2, 2)
    _noise: NoiseModel
    _clock: ClockModel
    _windows: WindowBuffer
    _time: float | None
    _next_id: int
    _reported: dict[int, set[int]]
    _clock_turn: int

    def _class_slot(self, class_id: np.ndarray) -> np.ndarray:
        """Index into the per-class arrays: the class id, or the last slot for unknown ids."""
        class_id = np.asarray(class_id, np.int64)
        return np.where((class_id >= 0) & (class_id < len(CLASS_NAMES)), class_id,
                        len(CLASS_NAMES))

    @staticmethod
    def _largest_boxes(
        observed: Observations, matched: np.ndarray, rows: np.ndarray, track_count: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Camera and box of each track's largest assigned box (the closest, best view)."""
        boxes = observed.xyxy[matched]
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        order = np.lexsort((area, rows))  # by track, then by area ascending
        last_of_track = np.r_[rows[order][1:] != rows[order][:-1], True]
        best = order[last_of_track]
        camera = np.full(track_count, -1, np.int64)
        box = np.full((track_count, 4), np.nan)
        camera[rows[best]] = observed.camera[matched][best]
        box[rows[best]] = boxes[best]
        return camera, box
