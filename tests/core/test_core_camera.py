"""Camera model: pixel <-> world round trips, the horizon, homography-only cameras."""

from __future__ import annotations

import numpy as np
import pytest
from core_cameras import posed_camera
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.camera import Camera
from cblrs.errors import CalibrationError
from cblrs.geometry import homography_pixel_to_world, rotation_from_pose

LENSES = {
    "pinhole": None,
    "barrel": np.array([-0.3, 0.08, 0.0, 0.0, 0.0]),
    "pincushion": np.array([0.2, 0.0, 0.001, -0.001, 0.0]),
}


@pytest.mark.parametrize("lens", list(LENSES))
@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(0, 639, allow_nan=False),
    y=st.floats(90, 359, allow_nan=False),
    height_m=st.sampled_from([0.0, 0.5, 1.7]),
)
def test_pixel_world_pixel_round_trip(lens, x, y, height_m):
    camera = posed_camera(distortion=LENSES[lens])
    pixels = np.array([[x, y]])
    world_xy, valid = camera.pixel_to_world(pixels, height_m)
    if not valid[0]:  # only near the horizon, which moves up with the plane height
        assert y < 140
        return
    back, back_valid = camera.world_to_pixel(world_xy, height_m)
    assert back_valid[0]
    np.testing.assert_allclose(back, pixels, atol=1e-3)
    # The 3D projection agrees with the plane homography.
    projected, _ = camera.project_points(np.column_stack([world_xy, [height_m]]))
    np.testing.assert_allclose(projected, pixels, atol=1e-3)


@pytest.mark.parametrize("lens", list(LENSES))
def test_world_pixel_world_round_trip(lens):
    camera = posed_camera(distortion=LENSES[lens])
    generator = np.random.default_rng(1)
    world_xy = generator.uniform([-4.0, -4.0], [4.0, 20.0], size=(500, 2))
    pixels, valid = camera.world_to_pixel(world_xy)
    seen = valid & camera.contains(pixels)
    assert seen.sum() > 200
    back, back_valid = camera.pixel_to_world(pixels[seen])
    assert back_valid.all()
    np.testing.assert_allclose(back, world_xy[seen], atol=1e-4)


def test_pixel_to_world_example_value():
    camera = Camera.from_pose("c", (0, 0, 10), 0, 45, 1000, (1920, 1080))
    world_xy, valid = camera.pixel_to_world([[959.5, 539.5]])
    assert valid[0]
    np.testing.assert_allclose(world_xy, [[10.0, 0.0]], atol=1e-9)


@pytest.mark.parametrize("lens", list(LENSES))
def test_pixels_above_the_horizon_are_invalid(lens):
    camera = posed_camera(distortion=LENSES[lens])
    # The horizon of the pinhole camera is at row 179.5 - 500 tan(12 deg) = 73.2.
    pixels = np.array([[320.0, 0.0], [10.0, 20.0], [630.0, 40.0], [320.0, 60.0]])
    world_xy, valid = camera.pixel_to_world(pixels)
    assert not valid.any()
    assert np.isnan(world_xy).all()
    below, below_valid = camera.pixel_to_world(np.array([[320.0, 200.0]]))
    assert below_valid.all() and np.isfinite(below).all()


def test_horizon_row_is_where_pinhole_validity_switches():
    camera = posed_camera()
    horizon = 179.5 - 500.0 * np.tan(np.radians(12.0))
    rows = np.array([horizon - 0.5, horizon - 1e-6, horizon + 1e-3, horizon + 0.5])
    _, valid = camera.pixel_to_world(np.column_stack([np.full(4, 320.0), rows]))
    assert valid.tolist() == [False, False, True, True]


def test_points_behind_the_camera_do_not_project():
    camera = posed_camera()
    pixels, valid = camera.world_to_pixel(np.array([[0.0, -20.0], [0.0, 0.0]]))
    assert valid.tolist() == [False, True]
    assert np.isnan(pixels[0]).all()


def test_homography_pixel_to_world_rejects_grazing_rays():
    camera = posed_camera()
    horizon = 179.5 - 500.0 * np.tan(np.radians(12.0))
    world_xy, valid = homography_pixel_to_world(
        camera.homography, np.array([[320.0, horizon + 1e-9], [np.nan, 200.0]])
    )
    assert not valid.any()
    assert np.isnan(world_xy).all()


@pytest.mark.parametrize("sign", [1.0, -1.0, 1e-4, -250.0])
def test_from_homography_fixes_the_sign(sign):
    posed = posed_camera()
    camera = Camera.from_homography("h", posed.homography * sign, posed.image_size)
    pixels = np.array([[320.0, 300.0], [10.0, 100.0], [320.0, 10.0]])
    expected, expected_valid = posed.pixel_to_world(pixels)
    world_xy, valid = camera.pixel_to_world(pixels)
    assert valid.tolist() == expected_valid.tolist() == [True, True, False]
    np.testing.assert_allclose(world_xy[valid], expected[valid], rtol=1e-9)


@pytest.mark.parametrize("sign", [1.0, -1.0, 3e-3, -40.0])
def test_from_projection_recovers_the_pose(sign):
    posed = posed_camera(distortion=None)
    projection = posed.intrinsics @ np.column_stack([posed.rotation, posed.translation])
    camera = Camera.from_projection("p", projection * sign, posed.image_size)
    np.testing.assert_allclose(camera.intrinsics, posed.intrinsics, atol=1e-9)
    np.testing.assert_allclose(camera.rotation, posed.rotation, atol=1e-12)
    np.testing.assert_allclose(camera.centre, [0.0, -12.0, 6.0], atol=1e-9)


def test_rotation_from_pose_is_a_rotation_looking_along_pan():
    rotation = rotation_from_pose(30.0, 45.0, 10.0)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    forward = rotation[2]  # camera z axis in world coordinates
    np.testing.assert_allclose(
        forward,
        [
            np.cos(np.radians(45)) * np.cos(np.radians(30)),
            np.cos(np.radians(45)) * np.sin(np.radians(30)),
            -np.sin(np.radians(45)),
        ],
        atol=1e-12,
    )


def test_planes_above_ground_need_a_pose():
    camera = Camera.from_homography("h", posed_camera().homography, (640, 360))
    assert camera.plane_homography(0.0) is camera.homography
    with pytest.raises(CalibrationError, match="known only by a homography"):
        camera.plane_homography(1.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"homography": np.zeros((3, 3))}, "the homography is singular"),
        ({"homography": np.eye(2)}, r"homography must have shape \(3, 3\)"),
        ({"homography": np.full((3, 3), np.nan)}, "NaN or infinite"),
        ({"image_size": (0, 100)}, "image size must be positive"),
        ({"distortion": np.array([0.1, 0, 0, 0])}, "lens distortion needs intrinsics"),
    ],
)
def test_invalid_cameras(kwargs, message):
    arguments = {"name": "bad", "image_size": (640, 360), "homography": np.eye(3)}
    arguments.update(kwargs)
    with pytest.raises(CalibrationError, match=message):
        Camera(**arguments)


def test_undistort_marks_folded_pixels_invalid():
    # k1 > 0 this strong folds the image corners over: they have no unique ideal position.
    camera = posed_camera(distortion=np.array([0.0, 0.0, 0.0, 0.0, -2.0]))
    undistorted = camera.undistort_pixels(np.array([[0.0, 0.0], [320.0, 180.0]]))
    assert np.isnan(undistorted[0]).all()
    np.testing.assert_allclose(undistorted[1], [320.0, 180.0], atol=1e-6)


def test_field_radius_is_where_the_radial_model_folds_back():
    # r (1 + k1 r^2) stops growing at r = 1 / sqrt(-3 k1).
    camera = posed_camera(distortion=np.array([-0.3, 0.0, 0.0, 0.0]))
    assert camera.field_radius == pytest.approx(1 / np.sqrt(0.9), abs=1e-3)
    assert posed_camera().field_radius == np.inf
    assert posed_camera(distortion=np.array([0.1, 0.0, 0.0, 0.0])).field_radius == np.inf
    # In front and within the field; beyond it; behind the camera.
    rotation, translation = camera._pose()
    camera_xyz = np.array([[0.5, 0.0, 1.0], [1.2, 0.0, 1.0], [0.1, 0.0, -1.0]])
    world = (camera_xyz - translation) @ rotation
    np.testing.assert_array_equal(camera.in_field(world), [True, False, False])
