"""Calibration from clicked points (cblrs.calibrate) and the pose of a homography."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.calibrate import (
    Correspondences,
    Model,
    calibrate_camera,
    estimate_focal,
    pose_from_homography,
)
from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.errors import CalibrationError

SIZE = (1280, 720)
TRUTH = Camera.from_pose("c", (-4.0, -4.0, 6.0), 37, 22, 1000, SIZE)
GRID = np.array([[x, y] for x in range(0, 31, 3) for y in range(0, 21, 3)], dtype=float)


def clicked(camera: Camera, count: int, noise_px: float = 0.0, seed: int = 0) -> Correspondences:
    """``count`` ground points the camera sees, spread over its image, with click noise."""
    from cblrs.experiments.calibration import spread_choice

    pixels, in_front = camera.world_to_pixel(GRID)
    seen = in_front & camera.contains(pixels)
    rng = np.random.default_rng(seed)
    chosen = spread_choice(pixels[seen], count, rng)
    noisy = pixels[seen][chosen] + rng.normal(0, noise_px, (count, 2))
    return Correspondences(noisy, GRID[seen][chosen])


@pytest.mark.parametrize(
    ("count", "focal", "model", "expected"),
    [
        (4, None, "auto", Model.HOMOGRAPHY),
        (5, 1000.0, "auto", Model.POSE),
        (6, None, "auto", Model.FOCAL),
        # 8 points allow k1, but points from a lens without distortion predict held-out
        # points no better with it: the simpler model.
        (8, None, "auto", Model.FOCAL),
        (12, None, "homography", Model.HOMOGRAPHY),
        (12, 1000.0, "pose", Model.POSE),
        (12, None, "focal", Model.FOCAL),
        (12, None, "k1", Model.K1),
    ],
)
def test_exact_points_give_the_camera_back(count, focal, model, expected):
    fit = calibrate_camera(clicked(TRUTH, count), SIZE, "c", focal_px=focal, model=model)
    assert fit.model is expected
    assert fit.rms_px < 1e-3
    assert np.nanmax(fit.error_m) < 1e-4
    # The fitted camera maps the whole ground like the true one, not just the clicked points.
    pixels, _ = TRUTH.world_to_pixel(GRID)
    fitted, _ = fit.camera.world_to_pixel(GRID)
    assert np.nanmax(np.hypot(*(fitted - pixels).T)) < 1e-2
    np.testing.assert_allclose(fit.position, (-4.0, -4.0, 6.0), atol=1e-3)
    if expected is not Model.HOMOGRAPHY:
        assert fit.camera.has_pose and fit.position_source == "pose"
        assert fit.focal_px == pytest.approx(1000.0, rel=1e-4)
    else:
        assert "homography" in fit.position_source


def test_k1_is_fitted_from_a_distorting_lens():
    lens = Camera.from_pose("c", (-4.0, -4.0, 6.0), 37, 22, 1000, SIZE, distortion=[-0.12, 0, 0, 0])
    points = clicked(lens, 14)
    homography_only = calibrate_camera(points, SIZE, "c", model="homography")
    fit = calibrate_camera(points, SIZE, "c")
    assert fit.model is Model.K1
    assert fit.camera.distortion[0] == pytest.approx(-0.12, abs=0.005)
    assert fit.rms_px < 0.05 < homography_only.rms_px


def test_noisy_clicks_on_a_real_wildtrack_camera(wildtrack_root):
    from cblrs.calibration import read_wildtrack_cameras

    camera = read_wildtrack_cameras(wildtrack_root)[0]
    world = np.array([[x, y] for x in np.arange(-3, 9.1, 1.5) for y in np.arange(-9, 27.1, 2.0)])
    pixels, in_front = camera.world_to_pixel(world)
    seen = in_front & camera.contains(pixels)
    rng = np.random.default_rng(1)
    chosen = rng.choice(np.flatnonzero(seen), 10, replace=False)
    points = Correspondences(pixels[chosen] + rng.normal(0, 2.0, (10, 2)), world[chosen])
    fit = calibrate_camera(points, camera.image_size, "CVLab1")
    # The frames are undistorted: k1 does not predict held-out points better.
    assert fit.model is Model.FOCAL and fit.warnings == ()
    assert set(fit.held_out) == {"homography", "focal", "k1"}
    assert 1.0 < fit.rms_px < 4.0
    assert np.linalg.norm(np.array(fit.position) - camera.centre) < 0.5
    assert fit.focal_px == pytest.approx(camera.intrinsics[0, 0], rel=0.1)


def test_an_outlier_is_reported_by_name_and_left_out():
    points = clicked(TRUTH, 9, noise_px=0.5)
    image = points.image_xy.copy()
    image[3] += (60.0, -40.0)
    names = tuple(f"p{index}" for index in range(9))
    fit = calibrate_camera(Correspondences(image, points.world_xy, names), SIZE, "c")
    assert fit.inliers.tolist() == [True] * 3 + [False] + [True] * 5
    assert any(re.search(r"p3 is an outlier \(\d+\.\d px from the fit\)", w) for w in fit.warnings)
    assert fit.error_px[3] > 50 and fit.rms_px < 2
    # The 8 inliers allow k1, but the lens has none: held out, k1 predicts no better.
    assert fit.model is Model.FOCAL and "k1" in fit.held_out


def test_a_large_error_is_warned_about():
    fit = calibrate_camera(clicked(TRUTH, 10, noise_px=12.0), SIZE, "c", ransac_px=200)
    assert any("large for model" in warning for warning in fit.warnings), fit.warnings


def test_four_points_warn_that_the_fit_is_exact():
    fit = calibrate_camera(clicked(TRUTH, 4, noise_px=1.0), SIZE, "c")
    assert any("determine a homography exactly" in warning for warning in fit.warnings)


ROWS = [
    [1099.9, 288.4, 16, 0],
    [16.1, 271.4, 4, 18],
    [521.4, 599.9, 2, 2],
    [608.1, 126.2, 26, 20],
    [343.0, 329.3, 6, 10],
    [807.5, 402.0, 8, 2],
    [122.1, 554.6, 0, 6],
]


@pytest.mark.parametrize(
    ("rows", "options", "message"),
    [
        (
            ROWS[:3],
            {},
            r"pts\.csv: 3 points cannot calibrate a camera; a ground homography needs "
            r"at least 4",
        ),
        (
            [[100 + 10 * i, 300 + 5 * i, 2 * i, 3 * i] for i in range(5)],
            {},
            r"the 5 world points lie on one line",
        ),
        (
            [[100, 300, 0, 0], [200, 300, 10, 0], [300, 300, 10, 10], [400, 300, 0, 10]],
            {},
            r"the 4 image points lie on one line",
        ),
        (
            [[100, 600, 0, 0], [600, 600, 5, 0], [1100, 600, 10, 0], [600, 200, 5, 10]],
            {},
            r"do not pin down a homography \(three of four",
        ),
        (
            [[100, 600, 0, 0], [1100, 600, 10, 0], [1000, 200, 10, 20], [300, 200, 20, 10]],
            {},
            r"row \d \(u, v = .*\) lies behind the camera under the fit of the other points",
        ),
        (
            ROWS[:7],
            {"model": "k1"},
            r"7 points cannot fit the pose, focal length and k1 \(model "
            r"k1 needs at least 8\)",
        ),
        (ROWS[:5], {"model": "focal"}, r"model focal needs at least 6"),
        (ROWS[:6], {"model": "pose"}, r"model pose keeps the focal length fixed, so it needs one"),
        (ROWS[:6], {"model": "fish"}, r"unknown model 'fish'"),
        (ROWS[:6], {"focal_px": -3.0}, r"the focal length must be a positive number"),
        ([*ROWS[:5], [float("nan"), 1, 2, 3]], {}, r"row 6: u, v must be finite numbers"),
        (
            [*ROWS[:5], [1, 2, float("inf"), 3]],
            {},
            r"row 6: x, y must be finite numbers \(a point "
            r"at infinity cannot be clicked\)",
        ),
    ],
)
def test_refused_fits_say_why_in_one_sentence(rows, options, message):
    with pytest.raises(CalibrationError, match=message) as error:
        calibrate_camera(Correspondences.from_rows(rows, "pts.csv"), SIZE, "c", **options)
    assert str(error.value).startswith("pts.csv: ") and "\n" not in str(error.value)


def test_csv_with_header_comments_and_names(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text(
        "# clicked on frame 12\nname,x,y,u,v\nbench,16,0,1099.9,288.4\n,4,18,16.1,271.4\n"
    )
    points = Correspondences.from_csv(path)
    assert points.names == ("bench", "row 2")
    np.testing.assert_array_equal(points.image_xy, [[1099.9, 288.4], [16.1, 271.4]])
    np.testing.assert_array_equal(points.world_xy, [[16, 0], [4, 18]])
    path.write_text("1099.9,288.4,16,0\n16.1,271.4,4,18,bin\n")
    assert Correspondences.from_csv(path).names == ("row 1", "bin")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("u,v,x,y,z\n1,2,3,4,5\n", r"p\.csv: unknown column 'z'"),
        ("1,2,3\n", r"p\.csv: row 1: expected u, v, x, y\[, name\]"),
        ("1,2,three,4\n", r"p\.csv: row 1: u, v, x, y must be numbers"),
        ("u,v,x,y\n1,2,3\n", r"p\.csv: row 1 has 3 values for 4 columns"),
    ],
)
def test_bad_csv_files(tmp_path, text, message):
    path = tmp_path / "p.csv"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=message):
        Correspondences.from_csv(path)


# ---------------------------------------------------------------------------- item 5


def test_pose_from_a_homography_with_a_known_focal_length():
    pose, reason = pose_from_homography(TRUTH.homography, SIZE, 1000.0)
    assert reason == "" and pose is not None and not pose.focal_estimated
    np.testing.assert_allclose(pose.camera.centre, (-4.0, -4.0, 6.0), atol=1e-9)
    np.testing.assert_allclose(pose.camera.rotation, TRUTH.rotation, atol=1e-12)


def test_pose_from_a_homography_of_any_scale_and_sign():
    pose, _ = pose_from_homography(-3.7 * TRUTH.homography, SIZE)
    assert pose is not None and pose.focal_estimated
    assert pose.focal_px == pytest.approx(1000.0, rel=1e-6)
    np.testing.assert_allclose(pose.camera.centre, (-4.0, -4.0, 6.0), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    x=st.floats(-20, 20),
    y=st.floats(-20, 20),
    height=st.floats(1.5, 30),
    pan=st.floats(-180, 180),
    tilt=st.floats(10, 70),
    roll=st.floats(-10, 10),
    focal=st.floats(400, 4000),
)
def test_estimated_focal_recovers_random_cameras(x, y, height, pan, tilt, roll, focal):
    camera = Camera.from_pose("c", (x, y, height), pan, tilt, focal, (1920, 1080), roll_deg=roll)
    assert estimate_focal(camera.homography, (1920, 1080)) == pytest.approx(focal, rel=1e-6)
    pose, _ = pose_from_homography(camera.homography, (1920, 1080))
    assert pose is not None
    np.testing.assert_allclose(pose.camera.centre, (x, y, height), atol=1e-6 * (1 + height))


def test_no_pose_when_none_can_be_had():
    down = Camera.from_pose("c", (0.0, 0.0, 10.0), 0, 90, 1000, SIZE)
    pose, reason = pose_from_homography(down.homography, SIZE)
    assert pose is None and "cannot be read from a homography without perspective" in reason
    pose, _ = pose_from_homography(down.homography, SIZE, 1000.0)
    assert pose is not None  # with the focal length given it is fine
    mirrored = TRUTH.homography @ np.diag([1.0, -1.0, 1.0])  # a left-handed world (y flipped)
    pose, reason = pose_from_homography(mirrored, SIZE, 1000.0)
    assert pose is None and "left-handed" in reason


def test_a_left_handed_world_is_refused_unless_said_so():
    points = clicked(TRUTH, 10)
    mirrored = Correspondences(points.image_xy, points.world_xy * [1, -1])
    with pytest.raises(CalibrationError, match=r"mirrored.*u and v, or x and y, swapped,"):
        calibrate_camera(mirrored, SIZE, "c")
    fit = calibrate_camera(mirrored, SIZE, "c", left_handed=True)
    assert fit.model is Model.HOMOGRAPHY and fit.position is None
    assert any(
        "below the ground" in warning and "left-handed" in warning for warning in fit.warnings
    )
    assert fit.rms_px < 1e-3


# ---------------------------------------------------------------------------- command


def test_calibrate_command_writes_the_camera_and_its_picture(tmp_path, capsys):
    import cv2

    points = clicked(TRUTH, 8, noise_px=1.0)
    csv = tmp_path / "gate.csv"
    csv.write_text(
        "u,v,x,y\n"
        + "".join(
            f"{u},{v},{x},{y}\n"
            for (u, v), (x, y) in zip(points.image_xy, points.world_xy, strict=True)
        )
    )
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.full((720, 1280, 3), 140, np.uint8))
    code = main(
        [
            "calibrate",
            str(csv),
            "--image",
            str(frame),
            "--out",
            str(tmp_path / "gate.json"),
            "--picture",
            str(tmp_path / "gate.png"),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "gate: model focal, 8/8 points" in out and "m high [pose]" in out
    picture = cv2.imread(str(tmp_path / "gate.png"))
    assert picture.shape == (720, 1280, 3)
    # Something was drawn: the grid, the points and the text differ from the plain frame.
    assert np.count_nonzero(np.any(picture != 140, axis=2)) > 5000
    from cblrs.calibration import read_cameras

    camera = read_cameras(tmp_path / "gate.json")[0]
    assert camera.has_pose and np.linalg.norm(camera.centre - (-4.0, -4.0, 6.0)) < 0.2


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--image-size", "1280x720", "--world", "map"], r"--world map needs the map's scale"),
        (["--image-size", "big"], r"--image-size 'big' must be WIDTHxHEIGHT"),
        (["--image", "none.png"], r"--image none\.png does not exist"),
        (["--image-size", "1280x720", "--picture", "x.jpg"], r"must be a \.png file"),
    ],
)
def test_calibrate_command_mistakes(tmp_path, capsys, monkeypatch, arguments, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.csv").write_text("\n".join(",".join(map(str, row)) for row in ROWS))
    assert main(["calibrate", "p.csv", *arguments]) != 0
    assert re.search(message, capsys.readouterr().err)


def test_calibrate_command_converts_map_pixels(tmp_path, capsys):
    points = clicked(TRUTH, 8)
    # world -> map pixels at 0.05 m per pixel, origin at map pixel (120, 880), y up
    map_px = np.column_stack(
        [120 + points.world_xy[:, 0] / 0.05, 880 - points.world_xy[:, 1] / 0.05]
    )
    (tmp_path / "p.csv").write_text(
        "".join(
            f"{u},{v},{x},{y}\n" for (u, v), (x, y) in zip(points.image_xy, map_px, strict=True)
        )
    )
    code = main(
        [
            "calibrate",
            str(tmp_path / "p.csv"),
            "--image-size",
            "1280x720",
            "--world",
            "map",
            "--metres-per-pixel",
            "0.05",
            "--map-origin",
            "120,880",
            "--json",
        ]
    )
    assert code == 0
    import json

    summary = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(summary["position"], (-4.0, -4.0, 6.0), atol=1e-3)
