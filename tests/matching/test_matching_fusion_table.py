"""Fusion tracker: the helpers every stage shares (:mod:`cblrs.matching.fusion.table`)."""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.fusion.table import TrackTable


def test_class_slot_sends_unknown_ids_to_the_last_slot():
    slots = TrackTable()._class_slot(np.array([0, len(CLASS_NAMES) - 1, -1, len(CLASS_NAMES), 99]))
    assert slots.tolist() == [0, len(CLASS_NAMES) - 1] + [len(CLASS_NAMES)] * 3


def test_largest_boxes_picks_each_tracks_biggest_view():
    boxes = np.array([[0, 0, 10, 10], [0, 0, 30, 30], [0, 0, 20, 20], [0, 0, 5, 5]], float)
    observed = Observations(
        world_xy=np.zeros((4, 2)), colour=np.zeros((4, 3), np.int64),
        camera=np.array([0, 1, 2, 3]), xyxy=boxes,
        class_id=np.zeros(4, np.int64), confidence=np.ones(4),
    )
    matched = np.array([True, True, True, False])
    rows = np.array([1, 1, 0])  # detections 0 and 1 went to track 1, detection 2 to track 0
    camera, box = TrackTable._largest_boxes(observed, matched, rows, track_count=3)
    assert camera.tolist() == [2, 1, -1]
    assert box[0].tolist() == [0, 0, 20, 20] and box[1].tolist() == [0, 0, 30, 30]
    assert np.isnan(box[2]).all()
