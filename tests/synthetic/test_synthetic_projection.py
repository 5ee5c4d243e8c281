"""Projection of oriented 3D boxes into camera images."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.camera import Camera
from cblrs.datasets.synthetic import (
    box_corners_3d,
    clip_boxes,
    project_box_3d,
    project_boxes_3d,
)

# Straight down from 10 m with a 500 px focal length: 1 m on the ground is 50 px; for pan 0
# the image x axis is world -y (see rotation_from_pose).
TOP = Camera.from_pose("top", (0.0, 0.0, 10.0), 0.0, 90.0, 500.0, (640, 480))


def test_flat_box_straight_down_is_its_scaled_footprint():
    xyxy, visible = project_box_3d(TOP, (0.0, 0.0), (2.0, 2.0, 0.0), 0.0)
    assert visible
    np.testing.assert_allclose(xyxy, [269.5, 189.5, 369.5, 289.5], atol=1e-9)


def test_tall_box_straight_down_is_bounded_by_its_top_face():
    # The top face at 1.75 m is 8.25 m from the camera: half-size 1 m -> 500 / 8.25 px.
    xyxy, visible = project_box_3d(TOP, (0.0, 0.0), (2.0, 2.0, 1.75), 0.0)
    half = 500.0 / 8.25
    assert visible
    np.testing.assert_allclose(xyxy, [319.5 - half, 239.5 - half, 319.5 + half, 239.5 + half])


def test_yaw_rotates_the_footprint():
    # A 4 x 1 footprint: along x at yaw 0 (image rows), along y at yaw 90 (image columns).
    along_x, _ = project_box_3d(TOP, (0.0, 0.0), (4.0, 1.0, 0.0), 0.0)
    along_y, _ = project_box_3d(TOP, (0.0, 0.0), (4.0, 1.0, 0.0), 90.0)
    assert along_x[3] - along_x[1] == pytest.approx(200.0)
    assert along_x[2] - along_x[0] == pytest.approx(50.0)
    assert along_y[2] - along_y[0] == pytest.approx(200.0)
    # At 45 degrees the footprint's bounding square is (4 + 1) / sqrt(2) m wide.
    diagonal, _ = project_box_3d(TOP, (0.0, 0.0), (4.0, 1.0, 0.0), 45.0)
    assert diagonal[2] - diagonal[0] == pytest.approx(50.0 * 5.0 / np.sqrt(2.0))


@pytest.mark.parametrize(
    ("centre", "expected_visible", "expected_xyxy"),
    [
        ((0.0, 0.0), True, [269.5, 189.5, 369.5, 289.5]),
        # Half off the left edge (image x = -world y * 50 + 319.5): clipped at -0.5.
        ((0.0, 6.4), True, [-0.5, 189.5, 49.5, 289.5]),
        ((0.0, 50.0), False, None),  # far outside the image
        ((-30.0, 0.0), False, None),
    ],
)
def test_clipping_and_visibility(centre, expected_visible, expected_xyxy):
    xyxy, visible = project_box_3d(TOP, centre, (2.0, 2.0, 0.0), 0.0)
    assert visible is expected_visible
    if expected_xyxy is None:
        assert np.isnan(xyxy).all()
    else:
        np.testing.assert_allclose(xyxy, expected_xyxy, atol=1e-9)


def test_box_entirely_behind_the_camera_is_invisible():
    camera = Camera.from_pose("side", (0.0, 0.0, 1.5), 0.0, 10.0, 800.0, (1280, 720))
    xyxy, visible = project_box_3d(camera, (-6.0, 0.0), (4.5, 1.8, 1.5), 0.0)
    assert not visible
    assert np.isnan(xyxy).all()


def test_box_partly_behind_the_camera_is_clipped_at_the_near_plane():
    # A car straddling a low camera: the part in front fills the lower image; no NaN leaks.
    camera = Camera.from_pose("side", (0.0, 0.0, 1.5), 0.0, 10.0, 800.0, (1280, 720))
    xyxy, visible = project_box_3d(camera, (0.5, 0.0), (4.5, 1.8, 1.5), 0.0)
    assert visible
    assert np.isfinite(xyxy).all()
    np.testing.assert_allclose(xyxy[[0, 2, 3]], [-0.5, 1279.5, 719.5])


def test_vectorised_matches_single_and_handles_empty_input():
    rng = np.random.default_rng(3)
    centres = rng.uniform(-6, 6, size=(25, 2))
    sizes = rng.uniform(0.3, 5, size=(25, 3))
    yaws = rng.uniform(-180, 180, size=25)
    xyxy, visible = project_boxes_3d(TOP, centres, sizes, yaws)
    for row in range(25):
        single, single_visible = project_box_3d(TOP, centres[row], sizes[row], yaws[row])
        assert single_visible == visible[row]
        np.testing.assert_allclose(single, xyxy[row])
    empty_xyxy, empty_visible = project_boxes_3d(TOP, np.zeros((0, 2)), (1.0, 1.0, 1.0), 0.0)
    assert empty_xyxy.shape == (0, 4) and empty_visible.shape == (0,)


def test_corners_have_the_box_dimensions():
    corners = box_corners_3d(np.array([[3.0, -2.0]]), (4.0, 2.0, 1.5), 30.0, base_z=0.5)[0]
    assert corners[:, 2].min() == pytest.approx(0.5) and corners[:, 2].max() == pytest.approx(2.0)
    np.testing.assert_allclose(corners[:4, :2].mean(axis=0), [3.0, -2.0])
    assert np.linalg.norm(corners[0] - corners[3]) == pytest.approx(4.0)  # length edge
    assert np.linalg.norm(corners[0] - corners[1]) == pytest.approx(2.0)  # width edge
    heading = corners[0, :2] - corners[3, :2]
    assert np.degrees(np.arctan2(heading[1], heading[0])) == pytest.approx(30.0)


@pytest.mark.parametrize(
    ("box", "expected", "nonempty"),
    [
        ([10, 10, 20, 20], [10, 10, 20, 20], True),
        ([-10, -10, 5, 5], [-0.5, -0.5, 5, 5], True),
        ([700, 10, 800, 20], [639.5, 10, 639.5, 20], False),
        ([np.nan] * 4, [np.nan] * 4, False),
    ],
)
def test_clip_boxes_table(box, expected, nonempty):
    clipped, keep = clip_boxes(np.array([box], dtype=float), (640, 480))
    np.testing.assert_allclose(clipped[0], expected)
    assert bool(keep[0]) is nonempty


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-4, 4),
    y=st.floats(-4, 4),
    yaw=st.floats(-180, 180),
    tilt=st.floats(20, 90),
    height=st.floats(0.2, 3.0),
)
def test_projected_box_contains_every_visible_corner(x, y, yaw, tilt, height):
    camera = Camera.from_pose("c", (-12.0, 0.0, 8.0), 0.0, tilt, 700.0, (960, 540))
    size = (2.0, 1.0, height)
    xyxy, visible = project_box_3d(camera, (x, y), size, yaw)
    corners = box_corners_3d(np.array([[x, y]]), size, yaw)[0]
    pixels, in_front = camera.project_points(corners)
    seen = in_front & camera.contains(np.nan_to_num(pixels, nan=-1e9))
    if seen.any():
        assert visible
        inside = pixels[seen]
        assert (inside[:, 0] >= xyxy[0] - 1e-6).all() and (inside[:, 0] <= xyxy[2] + 1e-6).all()
        assert (inside[:, 1] >= xyxy[1] - 1e-6).all() and (inside[:, 1] <= xyxy[3] + 1e-6).all()
