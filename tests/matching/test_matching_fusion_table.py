"""Fusion tracker: the helpers every stage shares (:mod:`cblrs.matching.fusion.table`)."""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.fusion.table import FusionContext, TrackTable, largest_boxes


def test_class_slot_sends_unknown_ids_to_the_last_slot():
    slots = FusionContext.class_slot(np.array([0, len(CLASS_NAMES) - 1, -1, len(CLASS_NAMES), 99]))
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
    camera, box = largest_boxes(observed, matched, rows, track_count=3)
    assert camera.tolist() == [2, 1, -1]
    assert box[0].tolist() == [0, 0, 20, 20] and box[1].tolist() == [0, 0, 30, 30]
    assert np.isnan(box[2]).all()


def test_track_table_selects_and_extends_every_column_alike():
    tracks = TrackTable.empty(models=2, cameras=3)
    assert len(tracks) == 0 and tracks.mode_state.shape == (0, 2, 4)
    one = TrackTable(
        ids=np.array([5, -1]), class_id=np.array([0, 2]), state=np.arange(8.0).reshape(2, 4),
        covariance=np.ones((2, 4, 4)), mode_state=np.zeros((2, 2, 4)),
        mode_covariance=np.zeros((2, 2, 4, 4)), mode_probability=np.full((2, 2), 0.5),
        evidence=np.array([3, 1]), last_seen=np.array([1.0, 2.0]),
        seen_by=np.full((2, 3), -np.inf), velocity_sigma=np.ones(2),
        heading=np.zeros((2, 2)), heading_time=np.full(2, -np.inf), heading_sigma=np.zeros(2),
    )
    both = tracks.extend(one).extend(one)
    assert len(both) == 4 and both.ids.tolist() == [5, -1, 5, -1]
    kept = both.select(np.array([False, True, True, False]))
    assert kept.ids.tolist() == [-1, 5] and kept.state[0].tolist() == [4.0, 5.0, 6.0, 7.0]
    assert all(len(column) == 2 for column in kept.columns())


def test_largest_boxes_of_a_few_boxes_picks_as_the_sorted_path(monkeypatch):
    """A window's few boxes are compared in Python, many through a sort; ties of area go to
    the later detection either way, and a NaN box takes the sorted path."""
    from cblrs.matching.fusion import table

    generator = np.random.default_rng(3)
    for trial in range(200):
        count = int(generator.integers(1, 40))
        boxes = generator.integers(0, 4, (count, 4)).astype(float)  # many equal areas
        if trial % 10 == 0:
            boxes[generator.integers(0, count), 1] = np.nan
        observed = Observations(
            world_xy=np.zeros((count, 2)), colour=np.zeros((count, 3), np.int64),
            camera=generator.integers(0, 5, count), xyxy=boxes,
            class_id=np.zeros(count, np.int64), confidence=np.ones(count),
        )
        matched = generator.random(count) < 0.7
        matched[0] = True
        rows = generator.integers(0, 8, int(matched.sum()))
        few = largest_boxes(observed, matched, rows, track_count=8)
        monkeypatch.setattr(table, "_FEW_BOXES", -1)
        sorted_path = largest_boxes(observed, matched, rows, track_count=8)
        monkeypatch.undo()
        np.testing.assert_array_equal(few[0], sorted_path[0])
        np.testing.assert_array_equal(few[1], sorted_path[1])
