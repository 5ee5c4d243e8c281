"""Boxes whose feet a nearer box hides get no location when the boxes are a detector's."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.detections import Detections
from cblrs.edge import feet_hidden, make_message, make_messages
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference


@pytest.mark.parametrize(
    ("boxes", "expected"),
    [
        ([], []),
        ([[100, 100, 140, 200]], [False]),
        # B stands in front of A's feet (reaches lower): A is hidden.
        ([[100, 100, 140, 200], [90, 120, 160, 300]], [True, False]),
        # Side by side, bottoms within 5 % of the height: nobody hides anybody.
        ([[100, 100, 140, 200], [120, 100, 160, 204]], [False, False]),
        # A's foot point is outside B horizontally.
        ([[100, 100, 140, 200], [125, 120, 200, 300]], [False, False]),
        # A head-and-shoulders box inside a whole person's box is hidden by it.
        ([[110, 100, 130, 140], [100, 95, 140, 250]], [True, False]),
    ],
)
def test_feet_hidden(boxes, expected):
    xyxy = np.array(boxes, float).reshape(-1, 4)
    pixels = np.column_stack([(xyxy[:, 0] + xyxy[:, 2]) / 2, xyxy[:, 3]])
    assert feet_hidden(xyxy, pixels, np.ones(len(xyxy))).tolist() == expected


def test_make_message_drops_hidden_feet_only_when_asked():
    camera = Camera.from_pose("c", (0.0, 0.0, 8.0), 0.0, 30.0, 1000.0, (640, 480))
    reference = render_reference(camera, PlaneSet([PlaneSpec(1, (0.0, -20.0), 40.0, 40.0)]))
    boxes = Detections(np.array([[300, 200, 330, 300], [290, 220, 360, 420]], float))
    kept = make_message("c", 0, 0.0, 0, boxes, reference)
    dropped = make_message("c", 0, 0.0, 0, boxes, reference, drop_hidden_feet=True)
    assert (kept.colour[:, 2] > 0).tolist() == [True, True]
    assert (dropped.colour[:, 2] > 0).tolist() == [False, True]
    np.testing.assert_array_equal(dropped.xyxy, boxes.xyxy)  # the box is still sent


@pytest.mark.parametrize(
    ("scores", "expected"),
    [
        # A sure nearer box hides the feet of any box, sure or not.
        ([0.9, 0.6], [True, False]),
        ([0.3, 0.6], [True, False]),
        # A doubtful nearer box (a bag, a shadow, a second box) does not take a sure box's
        # location...
        ([0.9, 0.3], [False, False]),
        # ...but still hides the feet of a box more doubtful than itself.
        ([0.2, 0.3], [True, False]),
        ([0.35, 0.3], [False, False]),
    ],
)
def test_feet_hidden_by_a_doubtful_box(scores, expected):
    xyxy = np.array([[100, 100, 140, 200], [90, 120, 160, 300]], float)
    pixels = np.column_stack([(xyxy[:, 0] + xyxy[:, 2]) / 2, xyxy[:, 3]])
    hidden = feet_hidden(xyxy, pixels, np.ones(2), confidence=np.array(scores))
    assert hidden.tolist() == expected


def test_make_message_and_make_messages_use_the_scores_alike():
    camera = Camera.from_pose("c", (0.0, 0.0, 8.0), 0.0, 30.0, 1000.0, (640, 480))
    reference = render_reference(camera, PlaneSet([PlaneSpec(1, (0.0, -20.0), 40.0, 40.0)]))
    xyxy = np.array([[300, 200, 330, 300], [290, 220, 360, 420]], float)
    doubtful_front = Detections(xyxy, confidence=np.array([0.9, 0.3]))
    sure_front = Detections(xyxy, confidence=np.array([0.3, 0.9]))
    one = make_message("c", 0, 0.0, 0, doubtful_front, reference, drop_hidden_feet=True)
    assert (one.colour[:, 2] > 0).tolist() == [True, True]
    many = make_messages("c", [(0, 0.0, 0), (1, 0.1, 1)], [doubtful_front, sure_front],
                         reference, drop_hidden_feet=True)
    np.testing.assert_array_equal(many[0].colour, one.colour)
    assert (many[1].colour[:, 2] > 0).tolist() == [False, True]
