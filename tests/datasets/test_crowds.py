"""Synthetic crowds: WILDTRACK's cameras over a dense crowd; barrel-distorted cameras."""

from __future__ import annotations

import numpy as np

from cblrs.datasets.crowds import (
    WILDTRACK_AREA,
    crowd_world,
    distorted_world,
    make_crowd_scene,
)
from cblrs.datasets.synthetic import SyntheticWorld


def test_crowd_is_dense_in_wildtracks_area_and_seen_by_its_cameras(wildtrack_root):
    scene = make_crowd_scene(wildtrack_root, seed=1, people=60)
    assert len(scene.cameras) == 7
    assert len(np.unique(scene.ground_truth.track_id)) == 60
    xy = scene.ground_truth.world_xy
    x_min, y_min, x_max, y_max = WILDTRACK_AREA
    assert (xy >= [x_min - 1e-9, y_min - 1e-9]).all() and (xy <= [x_max + 1e-9, y_max + 1e-9]).all()
    # Dense: at a typical frame most people have a neighbour within 1.5 m.
    frame = scene.ground_truth.world_xy[scene.ground_truth.frame == 100]
    gap = np.hypot(*(frame[:, None] - frame[None]).transpose(2, 0, 1))
    np.fill_diagonal(gap, np.inf)
    assert np.mean(gap.min(axis=1) < 1.5) > 0.5
    assert crowd_world(scene.cameras, 1).fps == 10.0


def test_distorted_cameras_report_boxes_in_distorted_pixels():
    world = distorted_world(seed=1, people=10, duration_s=2.0)
    assert all(camera.has_distortion for camera in world.cameras)
    assert world.cameras[0].distortion[0] == -0.3
    scene = SyntheticWorld(world).scene()
    pinhole = SyntheticWorld(
        distorted_world(seed=1, people=10, duration_s=2.0, k1=0.0)).scene()
    moved = []
    for with_lens, without in zip(scene.detections[5], pinhole.detections[5], strict=True):
        _, first, second = np.intersect1d(with_lens.object_id, without.object_id,
                                               return_indices=True)
        moved.extend(np.abs(with_lens.xyxy[first] - without.xyxy[second]).max(axis=1))
    assert len(moved) > 10 and np.median(moved) > 5.0  # pixels: the lens does move boxes


def test_distorted_cameras_see_nothing_past_the_lens_field():
    # Past its field (normalised radius 1.054 for k1 = -0.3) the lens model folds back and
    # would image people on pixels that show nearer ground; such boxes are not reported, so
    # every reported box's bottom centre locates its person within a couple of metres.
    world = distorted_world(seed=1, people=40, duration_s=3.0)
    scene = SyntheticWorld(world).scene()
    truth = scene.ground_truth
    errors = []
    for index, frame in enumerate(scene.frames):
        at = truth.frame == frame
        where = dict(zip(truth.track_id[at].tolist(), truth.world_xy[at], strict=True))
        for camera, boxes in zip(scene.cameras, scene.detections[index], strict=True):
            foot = np.column_stack([(boxes.xyxy[:, 0] + boxes.xyxy[:, 2]) / 2, boxes.xyxy[:, 3]])
            located, _ = camera.pixel_to_world(foot)
            true = np.array([where[int(one)] for one in boxes.object_id]).reshape(-1, 2)
            errors.extend(np.hypot(*(located - true).T))
    errors = np.asarray(errors)
    assert len(errors) > 1000
    finite = errors[np.isfinite(errors)]
    assert len(finite) > 0.97 * len(errors)
    assert finite.max() < 2.0
