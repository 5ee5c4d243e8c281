"""Clicked calibration under click and ground noise: refinement, outliers, model choice,
predicted error (cblrs.calibrate.refine / robust / select / uncertainty)."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from cblrs.calibrate import Correspondences, Model, calibrate_camera
from cblrs.calibrate.refine import (
    FOCAL,
    HOMOGRAPHY,
    K1,
    POSE,
    Parameterisation,
    PointNoise,
    normalised_errors,
)
from cblrs.calibrate.select import HeldOut, choose
from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.errors import CalibrationError
from cblrs.experiments.calibration import spread_choice

SIZE = (1280, 720)
TRUTH = Camera.from_pose("c", (-4.0, -4.0, 6.0), 37, 22, 1000, SIZE)
GRID = np.array([[x, y] for x in range(0, 31, 3) for y in range(0, 21, 3)], dtype=float)
FINE = np.array([[x, y] for x in np.arange(0, 30.1, 0.5) for y in np.arange(0, 20.1, 0.5)])


def noisy_clicks(
    camera: Camera,
    count: int,
    seed: int,
    click_px: float = 2.0,
    ground_m: float = 0.1,
    world: np.ndarray = GRID,
) -> Correspondences:
    """``count`` seen ground points spread over the image, with click and ground noise."""
    pixels, in_front = camera.world_to_pixel(world)
    seen = in_front & camera.contains(pixels)
    rng = np.random.default_rng(seed)
    chosen = spread_choice(pixels[seen], count, rng)
    return Correspondences(
        pixels[seen][chosen] + rng.normal(0, click_px, (count, 2)),
        world[seen][chosen] + rng.normal(0, ground_m, (count, 2)),
    )


def ground_errors(camera: Camera, truth: Camera, world: np.ndarray) -> np.ndarray:
    """Metres between each seen ground point and where ``camera`` locates its true pixel."""
    pixels, in_front = truth.world_to_pixel(world)
    seen = in_front & truth.contains(pixels)
    located, _ = camera.pixel_to_world(pixels[seen])
    return np.hypot(*(located - world[seen]).T)  # NaN where the fit sees no ground


# ---------------------------------------------------------------------------- the models


@pytest.mark.parametrize("model", [HOMOGRAPHY, POSE, FOCAL, K1])
def test_each_parameterisation_projects_like_its_camera(model):
    lens = Camera.from_pose("c", (-4.0, -4.0, 6.0), 37, 22, 1000, SIZE, distortion=[-0.1, 0, 0, 0])
    truth = TRUTH if model != K1 else lens
    pixels, _ = truth.world_to_pixel(GRID)
    parameterisation, params = Parameterisation.of_camera(model, truth, GRID, pixels)
    projected, depth = parameterisation.project(params, GRID)
    np.testing.assert_allclose(projected, pixels, atol=1e-6)
    assert np.all(depth > 0)
    back, _ = parameterisation.camera(params, "c").world_to_pixel(GRID)
    np.testing.assert_allclose(back, pixels, atol=1e-6)


def test_normalised_errors_weigh_a_pixel_error_by_where_the_point_lies():
    parameterisation, params = Parameterisation.of_camera(FOCAL, TRUTH, GRID, GRID)
    near, far = np.array([[2.0, 2.0]]), np.array([[27.0, 18.0]])
    scores = []
    for world in (near, far):
        pixels, _ = TRUTH.world_to_pixel(world)
        scores.append(
            normalised_errors(
                parameterisation, params, pixels + np.array([20.0, 0.0]), world, PointNoise()
            )
        )
    # 20 px near the camera is a few centimetres on the ground: well within 0.1 m of ground
    # noise; 20 px far away is metres.
    assert scores[0][0] < 6.0 < 13.8 < scores[1][0]


# ---------------------------------------------------------------------------- outliers


def test_a_near_point_far_off_in_pixels_but_close_on_the_ground_is_no_outlier():
    points = noisy_clicks(TRUTH, 10, seed=3, ground_m=0.02)
    pixels, _ = TRUTH.world_to_pixel(points.world_xy)
    nearest = int(np.argmax(pixels[:, 1]))  # lowest in the image: nearest the camera
    image = points.image_xy.copy()
    image[nearest] += (18.0, 0.0)
    fit = calibrate_camera(Correspondences(image, points.world_xy), SIZE, "c")
    assert fit.inliers.all(), fit.warnings
    farthest = int(np.argmin(pixels[:, 1]))
    image = points.image_xy.copy()
    image[farthest] += (18.0, 0.0)
    fit = calibrate_camera(Correspondences(image, points.world_xy), SIZE, "c")
    assert not fit.inliers[farthest] and fit.inliers.sum() == 9
    assert any(
        re.search(r"row \d+ is an outlier \(\d+\.\d px from the fit\)", w) for w in fit.warnings
    )
    # The old behaviour on request: one pixel threshold for every point.
    fit = calibrate_camera(Correspondences(image, points.world_xy), SIZE, "c", ransac_px=40.0)
    assert fit.inliers.all()


def test_a_distorting_lens_is_not_mistaken_for_outliers(wildtrack_distorted_cameras):
    # WILDTRACK's raw video lens: k1 about -0.5, the frame's edges far off any homography.
    camera = wildtrack_distorted_cameras[3]
    world = np.array([[x, y] for x in np.arange(-3, 9.1, 0.5) for y in np.arange(-9, 27.1, 0.5)])
    pixels, in_front = camera.world_to_pixel(world)
    ideal = np.column_stack([world, np.ones(len(world))]) @ camera.homography.T
    # Points the lens really shows (not folded in from outside the field of view).
    seen = in_front & camera.contains(pixels) & (ideal[:, 2] > 0)
    seen &= camera.contains(ideal[:, :2] / ideal[:, 2:3])
    rng = np.random.default_rng(0)
    chosen = spread_choice(pixels[seen], 12, rng)
    points = Correspondences(pixels[seen][chosen] + rng.normal(0, 2, (12, 2)), world[seen][chosen])
    homography = calibrate_camera(points, camera.image_size, "c", model="homography")
    fit = calibrate_camera(points, camera.image_size, "c")
    assert homography.inliers.sum() < 12  # the lens bends the frame's edges off a homography
    assert fit.model is Model.K1 and fit.inliers.all()
    assert fit.camera.distortion[0] < -0.15
    assert np.nanpercentile(ground_errors(fit.camera, camera, world[seen]), 95) < 0.5 * (
        np.nanpercentile(ground_errors(homography.camera, camera, world[seen]), 95)
    )


# ---------------------------------------------------------------------------- model choice


def test_k1_is_refused_when_held_out_points_do_not_improve():
    for seed in range(4):
        fit = calibrate_camera(noisy_clicks(TRUTH, 12, seed), SIZE, "c")
        assert fit.model is Model.FOCAL, (seed, {k: v.score for k, v in fit.held_out.items()})
        assert set(fit.held_out) == {"homography", "focal", "k1"}
        # k1 fits its own points at least as well, but gains nothing on held-out ones.
        assert (
            fit.held_out["k1"].score
            >= fit.held_out["focal"].score - fit.held_out["focal"].standard_error
        )


def test_k1_is_chosen_when_the_lens_distorts():
    lens = Camera.from_pose("c", (-4.0, -4.0, 6.0), 37, 22, 1000, SIZE, distortion=[-0.2, 0, 0, 0])
    fit = calibrate_camera(noisy_clicks(lens, 14, seed=1), SIZE, "c")
    assert fit.model is Model.K1
    assert fit.held_out["k1"].score < fit.held_out["focal"].score
    assert fit.camera.distortion[0] == pytest.approx(-0.2, abs=0.05)


def _held_out(model: str, scores: list[float]) -> HeldOut:
    distance = np.array(scores, dtype=float)
    return HeldOut(model, distance, np.sqrt(distance), np.zeros(len(distance)))


@pytest.mark.parametrize(
    ("scores", "expected"),
    [
        # Within one standard error of the best: the simplest.
        ({"homography": [2.0, 2.4, 2.2], "focal": [1.9, 2.3, 2.1], "k1": [1.6, 2.4, 2.0]}, "focal"),
        # A richer model that predicts held-out points clearly better wins.
        ({"focal": [9.0, 11.0, 10.0], "k1": [2.0, 2.1, 1.9]}, "k1"),
        # No noise at all: every score ~0, a tie.
        ({"homography": [0.0, 0.0], "focal": [1e-20, 0.0], "k1": [0.0, 0.0]}, "focal"),
        # A model that puts a held-out point behind the camera never wins.
        ({"focal": [np.inf, 1.0], "homography": [3.0, 3.0]}, "homography"),
        ({"focal": [np.inf, 1.0]}, None),
    ],
)
def test_the_one_standard_error_rule(scores, expected):
    assert choose({model: _held_out(model, values) for model, values in scores.items()}) == (
        expected
    )


# ---------------------------------------------------------------------------- accuracy


def test_ground_noise_is_weighed_and_beats_a_pixel_only_fit():
    better, ratios = 0, []
    for seed in range(20):
        points = noisy_clicks(TRUTH, 10, seed)
        fit = calibrate_camera(points, SIZE, "c", model="homography")
        plain, _ = cv2.findHomography(points.world_xy, points.image_xy, 0)
        ours = np.percentile(ground_errors(fit.camera, TRUTH, FINE), 95)
        pixel_only = np.percentile(
            ground_errors(Camera.from_homography("p", plain, SIZE), TRUTH, FINE), 95
        )
        better += ours < pixel_only
        ratios.append(ours / pixel_only)
    assert better >= 12 and np.mean(ratios) < 0.95


def test_the_chosen_model_is_bounded_on_a_known_camera_with_noise():
    worst, positions, covered, models = [], [], [], []
    for seed in range(20):
        points = noisy_clicks(TRUTH, 10, seed)
        fit = calibrate_camera(points, SIZE, "c")
        models.append(fit.model)
        low, high = points.world_xy.min(axis=0), points.world_xy.max(axis=0)
        between = FINE[np.all((FINE >= low) & (FINE <= high), axis=1)]
        pixels, in_front = TRUTH.world_to_pixel(between)
        seen = in_front & TRUTH.contains(pixels)
        located, _ = fit.camera.pixel_to_world(pixels[seen])
        errors = np.hypot(*(located - between[seen]).T)
        worst.append(float(np.nanmax(errors)))
        positions.append(float(np.linalg.norm(np.array(fit.position) - TRUTH.centre)))
        # The predicted error is an honest bound: the real one is within twice it.
        covered.append(float(np.mean(errors < 2 * fit.predicted_error_m(pixels[seen]))))
    # Measured: worst error between the points median 0.39 m, max 1.15 m; position error
    # at most 0.58 m; real error under twice the predicted one for 97 % of the ground.
    assert models.count(Model.K1) <= 2  # the lens has none (measured: once in 20)
    assert np.median(worst) < 0.6 and max(worst) < 1.6
    assert max(positions) < 1.0
    assert np.mean(covered) > 0.9


# ---------------------------------------------------------------------------- predicted error


def test_points_bunched_low_in_the_frame_warn_about_the_rest():
    pixels, in_front = TRUTH.world_to_pixel(FINE)
    seen = in_front & TRUTH.contains(pixels)
    near = seen & (pixels[:, 1] > 450)
    far = seen & (pixels[:, 1] < 200)
    rng = np.random.default_rng(0)
    chosen = np.concatenate(
        [
            np.flatnonzero(near)[spread_choice(pixels[near], 9, rng)],
            np.flatnonzero(far)[spread_choice(pixels[far], 1, rng)],
        ]
    )
    points = Correspondences(
        pixels[chosen] + rng.normal(0, 2, (10, 2)), FINE[chosen] + rng.normal(0, 0.1, (10, 2))
    )
    fit = calibrate_camera(points, SIZE, "c")
    coverage = fit.coverage
    assert coverage is not None and coverage.share > 0.02 and coverage.rows is not None
    assert coverage.rows[1] < 450  # the poorly constrained part lies above the clicks
    assert any(
        re.search(r"the predicted ground error exceeds 0\.5 m \(mostly rows \d+-\d+", warning)
        for warning in fit.warnings
    ), fit.warnings
    # Predicted error grows away from the points, towards the horizon.
    column = np.array([[640.0, 700.0], [640.0, 400.0], [640.0, 150.0]])
    predicted = fit.predicted_error_m(column)
    assert predicted[0] < predicted[1] < predicted[2]
    from cblrs.viz.calibration import calibration_picture, summary_lines

    picture = calibration_picture(fit, np.full((720, 1280, 3), 128, np.uint8))
    reddish = (picture[..., 0].astype(int) - picture[..., 2].astype(int)) > 40
    assert reddish[:150].mean() > 0.3 and reddish[600:].mean() < 0.01
    assert any(line.startswith("predicted ground error: median") for line in summary_lines(fit))
    assert any(line.startswith("held-out points") for line in summary_lines(fit))


def test_well_spread_points_do_not_warn():
    fit = calibrate_camera(noisy_clicks(TRUTH, 20, seed=2), SIZE, "c")
    assert fit.warnings == ()
    assert fit.coverage is not None and fit.coverage.share <= 0.02


# ---------------------------------------------------------------------------- options


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            {"click_px": 0.0},
            r"pts\.csv: the click noise must be a positive number of pixels, got 0",
        ),
        ({"ground_m": -1.0}, r"the ground noise must be a positive number of metres, got -1"),
        ({"ground_m": float("nan")}, r"the ground noise must be a positive number"),
        ({"warn_px": 0.0}, r"the warning threshold must be a positive number"),
    ],
)
def test_bad_noise_is_refused_in_one_sentence(options, message):
    clicks = noisy_clicks(TRUTH, 6, 0)
    points = Correspondences(clicks.image_xy, clicks.world_xy, source="pts.csv")
    with pytest.raises(CalibrationError, match=message) as error:
        calibrate_camera(points, SIZE, "c", **options)
    assert "\n" not in str(error.value)


def test_the_stated_noise_reaches_the_fit_from_the_command(tmp_path, capsys):
    import json

    points = noisy_clicks(TRUTH, 10, seed=4)
    csv = tmp_path / "p.csv"
    csv.write_text(
        "u,v,x,y\n"
        + "".join(
            f"{u},{v},{x},{y}\n"
            for (u, v), (x, y) in zip(points.image_xy, points.world_xy, strict=True)
        )
    )
    code = main(
        [
            "calibrate",
            str(csv),
            "--image-size",
            "1280x720",
            "--click-px",
            "1.5",
            "--ground-m",
            "0.05",
            "--json",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["noise"] == {"click_px": 1.5, "ground_m": 0.05}
    assert set(summary["held_out"]) == {"homography", "focal", "k1"}
    assert summary["predicted_error"]["limit_m"] == 0.5
    assert main(["calibrate", str(csv), "--image-size", "1280x720", "--ground-m", "0"]) != 0
    assert "the ground noise must be a positive number of metres" in capsys.readouterr().err
