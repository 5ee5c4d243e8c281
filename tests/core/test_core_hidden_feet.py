"""Boxes whose feet a nearer box hides get no location when the boxes are a detector's."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.detections import Detections
from cblrs.edge import feet_hidden, make_message
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
