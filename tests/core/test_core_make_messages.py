"""make_messages (a camera's frames at once) sends what make_message sends frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.detections import CLASS_NAMES, Detections
from cblrs.edge import make_message, make_messages
from cblrs.geometric_targeting import GeometricTargeter
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import OnDemandReference, render_reference

CAMERA = Camera.from_pose("c", (0.0, 0.0, 8.0), 0.0, 30.0, 1000.0, (640, 480))
PLANES = PlaneSet([PlaneSpec(1, (0.0, -20.0), 40.0, 40.0)])


def _frames(seed: int, count: int = 12) -> list[Detections]:
    """Frames of people and vehicles: overlapping, cut by the border, outside, empty."""
    generator = np.random.default_rng(seed)
    frames = []
    for index in range(count):
        boxes = int(generator.integers(0, 9)) if index % 5 else 0
        corner = generator.uniform([-60, 100], [640, 500], size=(boxes, 2))
        size = generator.uniform([20, 40], [160, 260], size=(boxes, 2))
        classes = generator.choice(
            [CLASS_NAMES.index(name) for name in ("person", "car", "bus", "bicycle")], boxes
        )
        frames.append(Detections(np.column_stack([corner, corner + size]),
                                 class_id=classes.astype(np.int64)))
    return frames


@pytest.mark.parametrize("drop_hidden_feet", [False, True])
@pytest.mark.parametrize("reference_kind", ["rendered", "on_demand"])
@pytest.mark.parametrize("with_targeter", [False, True])
def test_make_messages_equals_make_message_frame_by_frame(
    drop_hidden_feet, reference_kind, with_targeter
):
    reference = (render_reference(CAMERA, PLANES) if reference_kind == "rendered"
                 else OnDemandReference(CAMERA, PLANES))
    targeter = GeometricTargeter(CAMERA) if with_targeter else None
    detections = _frames(seed=3)
    headers = [(sequence, 0.1 * sequence + 5.0, 100 + 2 * sequence)
               for sequence in range(len(detections))]
    batch = make_messages("c", headers, detections, reference, targeter=targeter,
                          drop_hidden_feet=drop_hidden_feet)
    assert len(batch) == len(detections)
    located = 0
    for (sequence, timestamp, frame), boxes, message in zip(headers, detections, batch,
                                                            strict=True):
        single = make_message("c", sequence, timestamp, frame, boxes, reference,
                              targeter=targeter, drop_hidden_feet=drop_hidden_feet)
        assert (message.camera_id, message.sequence, message.timestamp, message.frame) == (
            "c", sequence, timestamp, frame)
        for column in ("xyxy", "confidence", "class_id", "colour"):
            np.testing.assert_array_equal(getattr(message, column), getattr(single, column))
        located += int((message.colour[:, 2] > 0).sum())
    assert located > 10  # the frames exercise the lookup, not only the refusals


def test_make_messages_edge_cases():
    reference = OnDemandReference(CAMERA, PLANES)
    assert make_messages("c", [], [], reference) == []
    with pytest.raises(ValueError, match="one set of detections per frame"):
        make_messages("c", [(0, 0.0, 0)], [], reference)
    empty = make_messages("c", [(0, 0.0, 0), (1, 0.1, 1)], [Detections.empty()] * 2, reference)
    assert [len(message) for message in empty] == [0, 0]
    assert empty[1].colour.shape == (0, 3)
