"""The tracker's targeting option: make_message(targeter=...) and track_scene(targeting=...)."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets.presets import make_scene
from cblrs.datasets.synthetic import project_boxes_3d
from cblrs.detections import Detections, class_id_of
from cblrs.edge import make_message
from cblrs.geometric_targeting import GeometricTargeter
from cblrs.pipeline import track_scene
from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference


def test_message_colour_is_the_footprint_centre():
    camera = Camera.from_pose("c", (0, 0, 8), 0, 40, 1200, (1920, 1080))
    centres, _ = camera.pixel_to_world([[800.0, 640.0], [1100.0, 700.0]])
    sizes = np.array([[4.5, 1.8, 1.5], [0.5, 0.5, 1.75]])
    xyxy, visible = project_boxes_3d(camera, centres, sizes, np.array([60.0, 0.0]))
    assert visible.all()
    detections = Detections(
        xyxy=xyxy,
        confidence=np.ones(2),
        class_id=np.array([class_id_of("car"), class_id_of("person")]),
        object_id=np.array([1, 2]),
    )
    plane = PlaneSpec(1, (0.0, -20.0), 40.0, 40.0, bits=16)
    reference = render_reference(camera, plane)
    message = make_message(
        "c", 0, 0.0, 0, detections, reference, targeter=GeometricTargeter(camera)
    )
    located, valid, _ = reference.planes.decode(message.colour)
    assert valid.all()
    assert np.hypot(*(located - centres).T).max() < 0.02
    default = make_message("c", 0, 0.0, 0, detections, reference)
    default_located, _, _ = reference.planes.decode(default.colour)
    # the person's default foot point lies in front of a box-shaped person's centre
    assert np.hypot(*(default_located[1] - centres[1])) > 0.1


def test_track_scene_with_geometric_targeting():
    scene = make_scene("plaza", duration_s=1.0)
    box = track_scene(scene)
    geometric = track_scene(scene, targeting="geometric")
    assert len(geometric.tracks) > 0
    assert geometric.detection_count == box.detection_count
    explicit = track_scene(scene, targeting=[GeometricTargeter(c) for c in scene.cameras])
    np.testing.assert_allclose(explicit.tracks.world_xy, geometric.tracks.world_xy)


@pytest.mark.parametrize(
    ("targeting", "message"),
    [("magic", "targeting must be 'box' or 'geometric'"), ([], "need one targeter per camera")],
)
def test_track_scene_rejects_bad_targeting(targeting, message):
    scene = make_scene("plaza", duration_s=0.5)
    with pytest.raises(ValueError, match=message):
        track_scene(scene, targeting=targeting)
