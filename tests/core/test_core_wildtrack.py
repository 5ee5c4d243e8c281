"""WILDTRACK: the calibration reader agrees with the annotations."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.calibration import WILDTRACK_CAMERAS
from cblrs.cli.locate import read_wildtrack_frame_boxes, wildtrack_position
from cblrs.locate import ColorLocator
from cblrs.targeting import target_pixels

FRAMES = (0, 250, 500, 750, 995)
# Median pixel distance between projected ground truth and box bottom centres, measured
# 2.7 .. 13.5 px over these frames; the bound leaves room without hiding a broken camera
# (a wrong unit or axis order gives hundreds of pixels).
MEDIAN_PIXEL_BOUND = 25.0


def foot_points(wildtrack_root, camera_name):
    """Box bottom centres (N, 2) and ground truth (N, 2) metres over FRAMES."""
    feet, truths = [], []
    for frame in FRAMES:
        boxes, _, truth = read_wildtrack_frame_boxes(wildtrack_root, frame, camera_name)
        feet.append(np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, boxes[:, 3]]))
        truths.append(truth)
    return np.concatenate(feet), np.concatenate(truths)


@pytest.mark.parametrize("view", range(7), ids=WILDTRACK_CAMERAS)
def test_ground_truth_projects_onto_box_bottoms(view, wildtrack_root, wildtrack_cameras):
    camera = wildtrack_cameras[view]
    feet, truth = foot_points(wildtrack_root, camera.name)
    pixels, valid = camera.world_to_pixel(truth)
    seen = valid & camera.contains(feet)
    assert seen.sum() >= 20
    error = np.hypot(*(pixels[seen] - feet[seen]).T)
    median = float(np.median(error))
    print(f"\n{camera.name}: median pixel error {median:.1f} px over {seen.sum()} boxes")
    assert median < MEDIAN_PIXEL_BOUND


@pytest.mark.parametrize("view", range(7), ids=WILDTRACK_CAMERAS)
def test_colour_lookup_of_box_feet_is_near_ground_truth(view, wildtrack_root, wildtrack_references):
    reference = wildtrack_references[view]
    boxes, _, truth = read_wildtrack_frame_boxes(wildtrack_root, 0, reference.camera_name)
    pixels, inside = target_pixels(boxes, 0.5, 1.0, reference.image_size)
    world_xy, valid = ColorLocator(reference).locate(pixels)
    usable = valid & inside
    error = np.hypot(*(world_xy[usable] - truth[usable]).T)
    assert np.median(error) < 0.5


def test_position_ids():
    np.testing.assert_allclose(
        wildtrack_position([0, 479, 480, 480 * 1440 - 1]),
        [[-3.0, -9.0], [-3.0 + 479 * 0.025, -9.0], [-3.0, -8.975], [8.975, 26.975]],
    )
