"""The realistic simulated detector: structured misses, truncated boxes, persistent false
positives."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.datasets.crowds import distorted_world
from cblrs.datasets.detector_model import DetectorModel, covered_fraction, realistic_detections
from cblrs.datasets.synthetic import SyntheticWorld
from cblrs.errors import DatasetError


@pytest.fixture(scope="module")
def scene():
    return SyntheticWorld(distorted_world(seed=2, people=40, duration_s=12.0)).scene()


def test_covered_fraction_counts_nearer_boxes_only():
    boxes = np.array([[0, 0, 10, 20], [0, 10, 10, 30], [100, 0, 110, 20]], float)
    covered, top = covered_fraction(boxes)
    assert covered.tolist() == [0.5, 0.0, 0.0]  # box 1 is nearer (lower bottom) than box 0
    assert top[0] == 10.0 and np.isnan(top[1:]).all()


def test_misses_follow_occlusion_and_persist(scene):
    degraded = realistic_detections(scene, seed=1, model=DetectorModel(
        false_sites=0, transient_false=0.0, truncation=0.0))
    kept_covered, kept_clear = [], []
    streaks = []
    for frame, row in enumerate(scene.detections):
        for camera, boxes in enumerate(row):
            covered, _ = covered_fraction(boxes.xyxy)
            found = np.isin(boxes.object_id, degraded.detections[frame][camera].object_id)
            kept_covered.extend(found[covered > 0.5])
            kept_clear.extend(found[covered == 0])
            if frame:
                before = scene.detections[frame - 1][camera]
                was_missed = ~np.isin(before.object_id,
                                      degraded.detections[frame - 1][camera].object_id)
                missed_then = before.object_id[was_missed]
                now = np.isin(boxes.object_id, missed_then)
                streaks.extend(~found[now])
    assert np.mean(kept_covered) < np.mean(kept_clear) - 0.2
    # A miss is followed by another miss far more often than the clear-box miss rate.
    assert np.mean(streaks) > 2 * (1 - np.mean(kept_clear))


def test_false_positives_persist_at_fixed_places_and_runs_are_seeded(scene):
    model = DetectorModel(miss=0.0, occluded_miss=0.0, far_miss=0.0, transient_false=0.0,
                          false_sites=1, false_site_rate=1.0)
    degraded = realistic_detections(scene, seed=3, model=model)
    false = [row[0].xyxy[row[0].object_id < 0] for row in degraded.detections]
    assert all(len(boxes) == 1 for boxes in false)
    centres = np.array([boxes[0, [0, 2]].mean() for boxes in false])
    assert centres.std() < 5.0  # the same place, frame after frame
    again = realistic_detections(scene, seed=3, model=model)
    assert np.array_equal(again.detections[7][2].xyxy, degraded.detections[7][2].xyxy)


def test_bad_rates_are_one_clear_sentence():
    with pytest.raises(DatasetError, match="occluded_miss must be in"):
        DetectorModel(occluded_miss=1.5)
