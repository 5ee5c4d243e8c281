"""Predictions outside the annotated area that match nobody are not scored."""

from __future__ import annotations

import numpy as np

from cblrs.detections import Tracks
from cblrs.evaluation.metrics import evaluate, outside_unmatched

AREA = (0.0, 0.0, 25.0, 16.0)


def _tracks(rows):
    rows = np.array(rows, float).reshape(-1, 4)
    return Tracks(rows[:, 0].astype(int), rows[:, 0] / 2, rows[:, 1].astype(int), rows[:, 2:])


def test_outside_unmatched_rows():
    truth = _tracks([[1, 1, 24.8, 8.0], [1, 2, 5.0, 5.0]])
    predicted = _tracks([
        [1, 10, 25.3, 8.0],  # outside, 0.5 m from a person at the border: scored
        [1, 11, 30.0, 8.0],  # outside, nobody near: not scored
        [1, 12, 12.0, 12.0],  # inside, nobody near: scored (a false positive)
        [2, 13, 40.0, 40.0],  # outside at a frame without ground truth
    ])
    assert outside_unmatched(truth, predicted, AREA).tolist() == [False, True, False, True]


def test_evaluate_with_an_area_ignores_unannotated_people_only():
    truth = _tracks([[frame, 1, 5.0 + frame, 5.0] for frame in range(5)])
    exact = _tracks([[frame, 7, 5.0 + frame, 5.0] for frame in range(5)])
    outsider = _tracks([[frame, 8, 30.0, 5.0] for frame in range(5)])
    insider = _tracks([[frame, 9, 15.0, 10.0] for frame in range(5)])
    both = Tracks.concatenate([exact, outsider])
    assert evaluate(truth, both, area=AREA).HOTA == evaluate(truth, exact).HOTA
    assert evaluate(truth, both).HOTA < evaluate(truth, exact).HOTA
    with_insider = Tracks.concatenate([exact, insider])
    assert evaluate(truth, with_insider, area=AREA).HOTA == evaluate(truth, with_insider).HOTA
