"""The paper matcher on hand-made messages."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.detections import CameraMessage
from cblrs.matching import MatcherError, PaperMatcher, make_matcher
from cblrs.plane import PlaneSet, PlaneSpec

SQUARE = PlaneSet([PlaneSpec(1, (0.0, 0.0), 20.0, 20.0)])
# Four times longer along y: one colour unit of G is four times the ground of one unit of R.
STRETCHED = PlaneSet([PlaneSpec(1, (0.0, 0.0), 10.0, 40.0)])


def message(planes: PlaneSet, camera: str, points: list[tuple[float, float]], frame: int = 0,
            timestamp: float = 0.0) -> CameraMessage:
    colour, valid = planes[0].encode(np.asarray(points, dtype=float).reshape(-1, 2))
    assert valid.all()
    count = len(colour)
    boxes = np.tile([100.0, 100.0, 140.0, 220.0], (count, 1))
    return CameraMessage(camera, frame, timestamp, frame, boxes, np.ones(count),
                         np.zeros(count, np.int64), colour.astype(np.int64))


def test_near_detection_joins_and_far_one_starts_an_object():
    matcher = PaperMatcher(SQUARE, ["a"], threshold_m=1.0)
    first = matcher.update(0.0, [message(SQUARE, "a", [(5, 5)])])
    second = matcher.update(0.5, [message(SQUARE, "a", [(5.5, 5), (12, 12)], frame=1)])
    assert first.track_id.tolist() == [1]
    assert second.track_id.tolist() == [1, 2]
    np.testing.assert_allclose(second.world_xy, [[5.5, 5], [12, 12]], atol=1e-3)
    assert second.frame.tolist() == [1, 1]
    assert matcher.object_count == 2


def test_hungarian_minimises_the_total_not_the_nearest_first():
    matcher = PaperMatcher(SQUARE, ["a"], threshold_m=1.0)
    matcher.update(0.0, [message(SQUARE, "a", [(5.0, 5.0), (6.2, 5.0)])])
    # Greedy nearest-first would give the detection at 5.7 to object 2 (0.5 away) and then
    # find object 1 too far (1.9) for the detection at 6.9; the Hungarian pairs both.
    result = matcher.update(0.5, [message(SQUARE, "a", [(5.7, 5.0), (6.9, 5.0)], frame=1)])
    by_id = dict(zip(result.track_id.tolist(), result.world_xy[:, 0].round(3).tolist(),
                     strict=True))
    assert by_id == {1: 5.7, 2: 6.9}
    assert matcher.object_count == 2


@pytest.mark.parametrize(
    ("space", "offset", "same_object"),
    [
        # threshold 1 m -> 1 / sqrt(step_x * step_y) = 1 / (2 step_x) colour units
        ("colour", (0.0, 0.8), True),  # 0.8 m along y is 0.2 / step_x units
        ("colour", (0.8, 0.0), False),  # 0.8 m along x is 0.8 / step_x units
        ("metres", (0.0, 0.8), True),
        ("metres", (0.8, 0.0), True),
    ],
)
def test_distance_is_measured_in_colour_units(space, offset, same_object):
    matcher = PaperMatcher(STRETCHED, ["a"], threshold_m=1.0, space=space)
    matcher.update(0.0, [message(STRETCHED, "a", [(5.0, 20.0)])])
    moved = (5.0 + offset[0], 20.0 + offset[1])
    result = matcher.update(0.5, [message(STRETCHED, "a", [moved], frame=1)])
    assert (result.track_id.tolist() == [1]) is same_object


def test_each_message_is_matched_in_turn_and_objects_are_never_deleted():
    matcher = PaperMatcher(SQUARE, ["a", "b"])
    matcher.update(0.0, [message(SQUARE, "a", [(3, 3)]), message(SQUARE, "b", [(3.4, 3)])])
    assert matcher.object_count == 1
    later = matcher.update(500.0, [message(SQUARE, "b", [(3.2, 3)], frame=1000)])
    assert later.track_id.tolist() == [1]
    assert later.camera_id.tolist() == [1]


@pytest.mark.parametrize("messages", [[], [CameraMessage.empty("a", 0, 0.0, 0)]])
def test_empty_input(messages):
    assert len(PaperMatcher(SQUARE, ["a"]).update(0.0, messages)) == 0


def test_detections_without_location_are_ignored():
    blank = CameraMessage("a", 0, 0.0, 0, np.array([[0.0, 0, 10, 10]]), np.ones(1),
                          np.zeros(1, np.int64), np.zeros((1, 3), np.int64))
    matcher = PaperMatcher(SQUARE, ["a"])
    assert len(matcher.update(0.0, [blank])) == 0
    assert matcher.object_count == 0


def test_state_round_trip_and_reset():
    steps = [[(1, 1), (5, 5)], [(1.3, 1), (5, 5.4)], [(1.6, 1), (9, 9)], [(1.9, 1)]]
    uninterrupted = PaperMatcher(SQUARE, ["a"])
    outputs = [uninterrupted.update(i * 0.5, [message(SQUARE, "a", points, frame=i)])
               for i, points in enumerate(steps)]
    first = PaperMatcher(SQUARE, ["a"])
    for i, points in enumerate(steps[:2]):
        first.update(i * 0.5, [message(SQUARE, "a", points, frame=i)])
    resumed = PaperMatcher(SQUARE, ["a"])
    resumed.set_state(json.loads(json.dumps(first.get_state())))
    for i, points in enumerate(steps[2:], start=2):
        output = resumed.update(i * 0.5, [message(SQUARE, "a", points, frame=i)])
        assert output.track_id.tolist() == outputs[i].track_id.tolist()
        np.testing.assert_array_equal(output.world_xy, outputs[i].world_xy)
    resumed.reset()
    again = resumed.update(0.0, [message(SQUARE, "a", steps[0])])
    assert again.track_id.tolist() == [1, 2]


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({"threshold_m": -1.0}, "threshold_m must be a positive number"),
        ({"threshold_m": float("nan")}, "threshold_m must be a positive number"),
        ({"space": "hsv"}, "space must be 'colour' or 'metres'"),
        ({"gate": 3}, "unknown option(s) for the paper matcher: gate"),
    ],
)
def test_bad_options(options, expected):
    with pytest.raises(MatcherError) as error:
        make_matcher("paper", SQUARE, ["a"], **options)
    assert expected in str(error.value)


def test_unknown_camera_and_bad_state():
    matcher = PaperMatcher(SQUARE, ["a"])
    with pytest.raises(MatcherError, match="unknown camera 'z'"):
        matcher.update(0.0, [message(SQUARE, "z", [(1, 1)])])
    with pytest.raises(MatcherError, match="not a saved paper-matcher state"):
        matcher.set_state({"version": "something else"})
    with pytest.raises(MatcherError, match="unknown matcher 'best'"):
        make_matcher("best", SQUARE, ["a"])
    with pytest.raises(MatcherError, match="camera ids must be distinct"):
        PaperMatcher(SQUARE, ["a", "a"])
