"""Tiles planned from the reference image, and merging the boxes of several tiles."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets import load_scene
from cblrs.datasets.images import read_image, scene_image_paths
from cblrs.detections import Detections
from cblrs.detectors import (
    ColourBlobDetector,
    OnnxDetector,
    TiledDetector,
    box_iou,
    plan_tiles,
    whole_frame_plan,
)
from cblrs.detectors.tiling import Tile, TilePlan, object_heights_px
from cblrs.errors import CblrsError
from cblrs.pipeline import render_scene_references
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference


@pytest.fixture(scope="module")
def multiviewx(multiviewx_real_root):
    scene = load_scene(multiviewx_real_root)
    return scene, render_scene_references(scene)


def test_object_heights_follow_the_camera_geometry():
    """A camera 6 m high with f = 1000 px: a 1.7 m person at depth d is ~1700 / d px tall."""
    camera = Camera.from_pose("c", (0.0, 0.0, 6.0), 0.0, 20.0, 1000.0, (1280, 720))
    reference = render_reference(camera, PlaneSet([PlaneSpec(1, (0.0, -40.0), 80.0, 80.0)]))
    u, v, heights = object_heights_px(reference, 1.7)
    world, valid = camera.pixel_to_world(np.column_stack([u, v]))
    depth = camera.to_camera_frame(np.column_stack([world, np.zeros(len(world))]))[:, 2]
    ratio = heights / (1000.0 * 1.7 / depth)
    # The estimate ignores the tilt's foreshortening (cos 20 deg = 0.94) and errs high by it.
    assert valid.all() and np.all((ratio > 0.9) & (ratio < 1.15))


def test_plans_of_the_real_cameras(multiviewx):
    _, references = multiviewx
    for reference in references:
        plan = plan_tiles(reference, (416, 416))
        assert plan.tiles[0].is_whole_frame
        scales = sorted({tile.scale for tile in plan.tiles})
        assert scales[0] == pytest.approx(416 / 1920)
        assert set(scales[1:]) <= {0.5, 1.0} and 1.0 in scales
        for tile in plan.tiles[1:]:
            assert 0 <= tile.x0 < tile.x1 <= 1920 and 0 <= tile.y0 < tile.y1 <= 1080
            assert tile.x1 - tile.x0 == round(416 / tile.scale)
            # Native tiles sit where the plane is far: above the image's middle.
            if tile.scale == 1.0:
                assert tile.y0 < 540
        assert 3 <= len(plan) <= 15
        assert "whole frame" in plan.describe()


def test_no_plane_in_view_means_the_whole_frame():
    camera = Camera.from_pose("c", (0.0, 0.0, 6.0), 0.0, 20.0, 1000.0, (1280, 720))
    reference = render_reference(camera, PlaneSet([PlaneSpec(1, (500.0, 500.0), 5.0, 5.0)]))
    plan = plan_tiles(reference, (416, 416))
    assert len(plan) == 1 and plan.tiles[0].is_whole_frame


class _BlobCandidates:
    """A detector with the tiled interface: red regions as person boxes."""

    iou = 0.45

    def __init__(self):
        self.blob = ColourBlobDetector((255, 0, 0), tolerance=10, min_area=4)
        self.crops: list[tuple[int, int]] = []

    def candidates(self, image):
        self.crops.append(image.shape[:2])
        return self.blob.detect(image)


def test_a_box_cut_by_an_inner_tile_edge_is_dropped_when_another_tile_holds_it_whole():
    image = np.zeros((200, 300, 3), np.uint8)
    image[50:90, 90:110] = (0, 0, 255)  # BGR red, across the edge x = 100
    image[150:170, 250:260] = (0, 0, 255)  # only in the right tile, at its border... inside
    left = Tile(0, 0, 100, 200, 1.0, (False, False, True, False))
    right = Tile(80, 0, 300, 200, 1.0, (True, False, False, False))
    detector = _BlobCandidates()
    tiled = TiledDetector(detector, TilePlan((300, 200), (100, 200), (left, right), 50.0))
    found = tiled.detect(image)
    assert detector.crops == [(200, 100), (200, 220)]
    assert sorted(found.xyxy.tolist()) == [[90.0, 50.0, 110.0, 90.0], [250.0, 150.0, 260.0, 170.0]]


def test_a_cut_box_nobody_holds_whole_is_kept():
    image = np.zeros((200, 300, 3), np.uint8)
    image[50:90, 90:110] = (0, 0, 255)
    left = Tile(0, 0, 100, 200, 1.0, (False, False, True, False))
    right = Tile(100, 0, 300, 200, 1.0, (True, False, False, False))
    tiled = TiledDetector(_BlobCandidates(), TilePlan((300, 200), (100, 200), (left, right), 50))
    found = tiled.detect(image)
    assert sorted(found.xyxy.tolist()) == [[90.0, 50.0, 100.0, 90.0], [100.0, 50.0, 110.0, 90.0]]


def test_frames_of_another_size_are_refused():
    tiled = TiledDetector(_BlobCandidates(), whole_frame_plan((300, 200), (100, 100)))
    with pytest.raises(CblrsError, match="the frame is 200x100 but the tile plan"):
        tiled.detect(np.zeros((100, 200, 3), np.uint8))
    assert len(tiled.detect(np.zeros((200, 300, 3), np.uint8))) == 0
    assert isinstance(tiled.detect(np.zeros((200, 300, 3), np.uint8)), Detections)


def test_tiles_find_more_of_the_annotated_people_than_the_whole_frame(
    multiviewx, multiviewx_real_root, yolox_model
):
    """The point of tiling, on two real frames of the six cameras (IoU >= 0.5 recall)."""
    scene, references = multiviewx
    paths = scene_image_paths(multiviewx_real_root, len(scene.cameras), scene.frames[:2])
    detector = OnnxDetector(yolox_model)
    recalls = {}
    for name in ("whole", "tiles"):
        matched = total = 0
        for position, row in enumerate(paths):
            for camera, path in enumerate(row):
                plan = (
                    whole_frame_plan(references[camera].image_size, detector.input_size)
                    if name == "whole" else plan_tiles(references[camera], detector.input_size)
                )
                found = TiledDetector(detector, plan).detect(read_image(path))
                truth = scene.detections[position][camera].xyxy
                if len(found):
                    matched += int((box_iou(truth, found.xyxy).max(axis=1) >= 0.5).sum())
                total += len(truth)
        recalls[name] = matched / total
    assert recalls["tiles"] > recalls["whole"] + 0.15, recalls


def test_real_detector_boxes_cut_or_off_the_plane_carry_no_location(
    multiviewx, multiviewx_real_root, yolox_model
):
    """Near people cut by the bottom border and people off the plane get colour 0; the
    located ones stand where annotated people stand (or outside the annotated area)."""
    from cblrs.edge import make_message

    scene, references = multiviewx
    frames = scene.frames[4:6]  # near people walk out of the bottom of the images here
    paths = scene_image_paths(multiviewx_real_root, len(scene.cameras), frames)
    detector = OnnxDetector(yolox_model)
    cut = off_plane = 0
    distances = []
    for position, row in enumerate(paths):
        truth = scene.ground_truth[scene.ground_truth.frame == frames[position]]
        for camera, path in enumerate(row):
            reference = references[camera]
            found = TiledDetector(detector, plan_tiles(reference, detector.input_size)).detect(
                read_image(path)
            )
            message = make_message("c", 0, 0.0, 0, found, reference, drop_hidden_feet=True)
            located, valid, _ = reference.planes.decode(message.colour)
            bottom = found.xyxy[:, 3] >= reference.image_size[1] - 1
            assert not valid[bottom].any()
            cut += int(bottom.sum())
            pixels = np.column_stack([(found.xyxy[:, 0] + found.xyxy[:, 2]) / 2, found.xyxy[:, 3]])
            seen = reference.colours_at(np.minimum(pixels, [1919, 1079]))[0][:, 2] > 0
            off_plane += int((~seen & ~bottom).sum())
            inside = valid & (located[:, 0] >= 0) & (located[:, 0] <= 25)
            inside &= (located[:, 1] >= 0) & (located[:, 1] <= 16)
            for point in located[inside]:
                distances.append(np.min(np.linalg.norm(truth.world_xy - point, axis=1)))
    assert cut > 0 and off_plane > 0  # both happen on these frames
    assert np.median(distances) < 0.3
