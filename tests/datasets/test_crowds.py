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
