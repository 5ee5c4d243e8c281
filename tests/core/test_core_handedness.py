"""Left-handed calibrations: the real MultiviewX files, and mirrored cameras built here.

MultiviewX publishes extrinsics in Unity's left-handed world: every ground point has negative
depth. The readers convert such cameras to ``R' = -R diag(1, 1, -1)``, ``t' = -t`` with the
height axis mirrored; these tests check, on the real files, that the conversion reprojects
exactly what the published extrinsics do, that heights still mean "above the ground", and
that rendering, localisation and tracking then work.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs.calibration import (
    MULTIVIEWX_GROUND,
    camera_from_dict,
    camera_to_dict,
    read_camera_json,
    read_multiviewx_cameras,
    read_opencv_matrices,
)
from cblrs.camera import Camera
from cblrs.datasets import load_scene
from cblrs.edge import make_message
from cblrs.evaluation.metrics import evaluate
from cblrs.handedness import ground_depth_sign, orient_to_ground
from cblrs.pipeline import render_scene_references, track_scene


@pytest.fixture(scope="module")
def scene(multiviewx_real_root: Path):
    return load_scene(multiviewx_real_root)


@pytest.fixture(scope="module")
def references(scene):
    return render_scene_references(scene)


def _published(root: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """rvec, tvec, K, distortion exactly as the MultiviewX files give them."""
    intrinsic = read_opencv_matrices(
        root / "calibrations" / "intrinsic" / f"intr_{name}.xml",
        ("camera_matrix", "distortion_coefficients"),
    )
    extrinsic = read_opencv_matrices(
        root / "calibrations" / "extrinsic" / f"extr_{name}.xml", ("rvec", "tvec")
    )
    return (
        extrinsic["rvec"].ravel(),
        extrinsic["tvec"].ravel(),
        intrinsic["camera_matrix"].reshape(3, 3),
        intrinsic["distortion_coefficients"].ravel(),
    )


def test_published_extrinsics_put_the_ground_behind_every_camera(multiviewx_real_root: Path):
    """The trap itself: with the files as published, the annotated area has negative depth."""
    x0, y0, width, length = MULTIVIEWX_GROUND
    grid = np.array([[x, y, 0.0] for x in np.linspace(x0, x0 + width, 11)
                     for y in np.linspace(y0, y0 + length, 9)])
    for number in range(1, 7):
        rvec, tvec, _, _ = _published(multiviewx_real_root, f"Camera{number}")
        rotation = cv2.Rodrigues(rvec)[0]
        depth = (grid @ rotation.T + tvec)[:, 2]
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        # Points of the area the camera sees (within 30 m) are all behind it.
        assert np.median(depth) < 0


def test_readers_convert_all_six_cameras_with_one_warning(
    multiviewx_real_root: Path, caplog: pytest.LogCaptureFixture
):
    with caplog.at_level(logging.WARNING, logger="cblrs.calibration"):
        cameras = read_multiviewx_cameras(multiviewx_real_root)
    warnings = [record for record in caplog.records if record.levelno == logging.WARNING]
    assert len(warnings) == 1
    message = warnings[0].getMessage()
    assert "left-handed" in message
    for number in range(1, 7):
        assert f"Camera{number}" in message
    for camera in cameras:
        assert camera.height_axis == -1
        assert np.linalg.det(camera.rotation) == pytest.approx(1.0, abs=1e-9)
        assert ground_depth_sign(camera, MULTIVIEWX_GROUND) == 1
        # Heights stay heights: the cameras stand 2.5 m above the ground.
        assert camera.centre[2] == pytest.approx(2.5, abs=0.01)


def test_conversion_reprojects_every_point_exactly_as_published(multiviewx_real_root: Path):
    """Ground points and points above it land on the pixel cv2.projectPoints gives for the
    published rvec/tvec (whose negative depth cv2 ignores), distortion included."""
    cameras = {camera.name: camera for camera in read_multiviewx_cameras(multiviewx_real_root)}
    rng = np.random.default_rng(0)
    world = np.column_stack(
        [rng.uniform(0, 25, 400), rng.uniform(0, 16, 400), rng.uniform(0, 2.0, 400)]
    )
    world[:200, 2] = 0.0
    for name, camera in cameras.items():
        rvec, tvec, matrix, distortion = _published(multiviewx_real_root, name)
        expected = cv2.projectPoints(world, rvec, tvec, matrix, distortion)[0].reshape(-1, 2)
        published_depth = (world @ cv2.Rodrigues(rvec)[0].T + tvec)[:, 2]
        # In front of the real camera and in its view before the lens model (far outside
        # it the polynomial lens model folds points back into the image).
        pinhole = cv2.projectPoints(world, rvec, tvec, matrix, None)[0].reshape(-1, 2)
        seen = (published_depth < -0.5) & camera.contains(pinhole)
        pixels, valid = camera.project_points(world)
        assert valid[seen].all()
        np.testing.assert_allclose(pixels[seen], expected[seen], atol=1e-6)
        # The ground mapping agrees too, both ways.
        ground = seen & (world[:, 2] == 0)
        pixels, valid = camera.world_to_pixel(world[ground, :2])
        assert valid.all()
        np.testing.assert_allclose(pixels, expected[ground], atol=1e-6)
        inside = camera.contains(pixels)
        back, valid = camera.pixel_to_world(pixels[inside])
        assert valid.all()
        np.testing.assert_allclose(back, world[ground][inside, :2], atol=1e-4)


def test_annotated_foot_points_reproject_onto_their_boxes(scene):
    """Ground truth positions project to the bottom centre of their (uncut) boxes within a
    few pixels, and a point 1.7 m above them lands near the box top."""
    truth = scene.ground_truth
    for index, camera in enumerate(scene.cameras):
        foot_errors, head_offsets = [], []
        for position, frame in enumerate(scene.frames):
            boxes = scene.detections[position][index]
            rows = truth[truth.frame == frame]
            for box, person in zip(boxes.xyxy, boxes.object_id, strict=True):
                if box[3] >= camera.image_size[1] - 1:
                    continue  # cut at the bottom: no foot point to compare with
                x, y = rows.world_xy[rows.track_id == person][0]
                pixel, valid = camera.world_to_pixel([[x, y]])
                assert valid[0]
                centre_x = (box[0] + box[2]) / 2
                foot_errors.append(np.hypot(pixel[0, 0] - centre_x, pixel[0, 1] - box[3]))
                head, _ = camera.project_points([[x, y, 1.7]])
                head_offsets.append(head[0, 1] - box[1])
        assert len(foot_errors) > 50
        assert np.median(foot_errors) < 10.0, camera.name
        assert 0.0 < np.median(head_offsets) < 25.0, camera.name


def test_render_coverage_is_positive_for_all_six_cameras(references):
    assert len(references) == 6
    for reference in references:
        assert reference.coverage() > 0.3


def test_annotated_boxes_locate_within_centimetres(scene, references):
    truth = scene.ground_truth
    errors = []
    located = total = 0
    for position, frame in enumerate(scene.frames):
        rows = truth[truth.frame == frame]
        for camera, reference, boxes in zip(
            scene.cameras, references, scene.detections[position], strict=True
        ):
            message = make_message(camera.name, 0, 0.0, int(frame), boxes, reference)
            world_xy, valid, _ = reference.planes.decode(message.colour)
            total += len(boxes)
            located += int(valid.sum())
            for row in np.flatnonzero(valid):
                expected = rows.world_xy[rows.track_id == boxes.object_id[row]][0]
                errors.append(np.linalg.norm(world_xy[row] - expected))
    # Boxes cut by the bottom border carry no location; nearly all others do.
    assert located / total > 0.97
    assert np.median(errors) < 0.15
    assert np.percentile(errors, 90) < 0.3


def test_tracking_the_annotated_boxes_meets_hota_93(scene, references):
    result = track_scene(scene, "fusion", references=references)
    metrics = evaluate(scene.ground_truth, result.tracks)
    assert metrics.HOTA >= 93.0, metrics.to_dict()


def test_converted_camera_survives_the_json_round_trip(multiviewx_real_root: Path, tmp_path):
    camera = read_multiviewx_cameras(multiviewx_real_root)[0]
    data = camera_to_dict(camera)
    assert data["height_axis"] == -1
    again = camera_from_dict(data)
    world = np.array([[5.0, 5.0, 0.0], [10.0, 3.0, 1.5]])
    np.testing.assert_allclose(again.project_points(world)[0], camera.project_points(world)[0])
    np.testing.assert_allclose(again.centre, camera.centre)
    # A left-handed description in a cblrs JSON file is converted on reading, too.
    rvec, tvec, matrix, distortion = _published(multiviewx_real_root, "Camera1")
    path = tmp_path / "left.json"
    import json

    path.write_text(json.dumps({
        "name": "Camera1", "image_size": [1920, 1080], "intrinsics": matrix.tolist(),
        "distortion": distortion.tolist(), "rvec": rvec.tolist(), "tvec": tvec.tolist(),
    }))
    (read,) = read_camera_json(path)
    assert read.height_axis == -1
    np.testing.assert_allclose(read.project_points(world)[0], camera.project_points(world)[0])


# ---------------------------------------------------------------- mirrored cameras built here


def _left_handed(camera: Camera) -> Camera:
    """The same camera described the MultiviewX way: world y mirrored (so that (x, y, up)
    is left-handed as the camera sees it) and the extrinsics negated to keep R a proper
    rotation, ``R_p = -R diag(1, -1, 1)``, ``t_p = -t``. Every depth is then negative."""
    mirror_y = np.diag([1.0, -1.0, 1.0])
    return Camera.from_extrinsics(
        camera.name, camera.intrinsics, -camera.rotation @ mirror_y, -camera.translation,
        camera.image_size, distortion=camera.distortion,
    )


@pytest.mark.parametrize(
    ("pan", "tilt", "height", "distortion"),
    [
        (0.0, 30.0, 8.0, None),
        (135.0, 12.0, 2.5, [-0.2, 0.05, 0.0, 0.0, 0.0]),
        (-60.0, 75.0, 20.0, None),
    ],
)
def test_a_left_handed_camera_converts_to_an_equivalent_proper_one(pan, tilt, height, distortion):
    proper = Camera.from_pose("c", (3.0, -4.0, height), pan, tilt, 1100.0, (1280, 720),
                              distortion=None if distortion is None else np.array(distortion))
    left = _left_handed(proper)
    assert np.linalg.det(left.rotation) == pytest.approx(1.0)
    assert ground_depth_sign(left) == -1 and ground_depth_sign(proper) == 1
    converted, changed = orient_to_ground(left)
    assert changed and converted.height_axis == -1
    assert np.linalg.det(converted.rotation) == pytest.approx(1.0)
    unchanged, changed = orient_to_ground(proper)
    assert not changed and unchanged is proper
    rng = np.random.default_rng(1)
    ground = proper.pixel_to_world(
        np.column_stack([rng.uniform(0, 1279, 50), rng.uniform(400, 719, 50)])
    )[0]
    ground = ground[np.isfinite(ground).all(axis=1)]
    real = np.column_stack([ground, rng.uniform(0, 1.9, len(ground))])
    published = real * np.array([1.0, -1.0, 1.0])  # the left-handed world's coordinates
    # Same pixel, positive depth, same heights (above the ground) as the real camera.
    np.testing.assert_allclose(
        converted.project_points(published)[0], proper.project_points(real)[0], atol=1e-6
    )
    np.testing.assert_allclose(
        converted.to_camera_frame(published)[:, 2], proper.to_camera_frame(real)[:, 2]
    )
    np.testing.assert_allclose(converted.centre, proper.centre * [1.0, -1.0, 1.0], atol=1e-9)
    pixels = proper.project_points(real)[0]
    for level in (0.0, 1.0):
        located, valid = converted.pixel_to_world(pixels, height_m=level)
        expected, expected_valid = proper.pixel_to_world(pixels, height_m=level)
        np.testing.assert_array_equal(valid, expected_valid)
        np.testing.assert_allclose(located[valid], expected[valid] * [1.0, -1.0], atol=1e-6)


def test_height_axis_must_be_a_sign():
    from cblrs.errors import CalibrationError

    camera = Camera.from_pose("c", (0.0, 0.0, 5.0), 0.0, 30.0, 900.0, (640, 480))
    with pytest.raises(CalibrationError, match="height_axis must be 1 or -1"):
        Camera.from_extrinsics("c", camera.intrinsics, camera.rotation, camera.translation,
                               (640, 480), height_axis=0)


def test_a_site_file_with_published_multiviewx_extrinsics_is_converted(
    multiviewx_real_root: Path, tmp_path, caplog: pytest.LogCaptureFixture
):
    from cblrs.site.core import site_from_document

    rvec, tvec, matrix, distortion = _published(multiviewx_real_root, "Camera1")
    document = {
        "version": 1,
        "planes": [{"id": 1, "origin": [-2, -2], "size": [29, 20]}],
        "cameras": [{
            "name": "Camera1", "image_size": [1920, 1080], "intrinsics": matrix.tolist(),
            "distortion": distortion.tolist(), "rvec": rvec.tolist(), "tvec": tvec.tolist(),
        }],
    }
    with caplog.at_level(logging.WARNING, logger="cblrs.calibration"):
        camera = site_from_document(document, tmp_path / "site.yaml").camera("Camera1").camera
    assert camera.height_axis == -1 and "left-handed" in caplog.text
    reference = read_multiviewx_cameras(multiviewx_real_root)[0]
    world = np.array([[5.0, 5.0, 0.0], [10.0, 3.0, 1.5]])
    np.testing.assert_allclose(camera.project_points(world)[0], reference.project_points(world)[0])
