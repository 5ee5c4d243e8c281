"""Calibration readers: WILDTRACK/MultiviewX XML, OpenCV FileStorage, AI City, cblrs JSON."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from core_cameras import posed_camera

from cblrs.calibration import (
    MULTIVIEWX_GROUND,
    WILDTRACK_CAMERAS,
    WILDTRACK_GROUND,
    calibration_layout,
    camera_to_dict,
    default_ground,
    read_aicity_calibration,
    read_camera_json,
    read_cameras,
    read_opencv_camera,
    read_opencv_matrices,
)
from cblrs.camera import Camera
from cblrs.errors import CalibrationError

PIXELS = np.array([[320.0, 300.0], [20.0, 200.0], [600.0, 350.0], [320.0, 10.0]])


def assert_same_geometry(camera: Camera, expected: Camera, atol: float = 1e-6) -> None:
    world_xy, valid = camera.pixel_to_world(PIXELS)
    expected_xy, expected_valid = expected.pixel_to_world(PIXELS)
    assert valid.tolist() == expected_valid.tolist()
    np.testing.assert_allclose(world_xy[valid], expected_xy[valid], atol=atol)


# ---------------------------------------------------------------------- WILDTRACK
def test_wildtrack_cameras(wildtrack_root, wildtrack_cameras, wildtrack_distorted_cameras):
    assert [camera.name for camera in wildtrack_cameras] == list(WILDTRACK_CAMERAS)
    for camera, distorted in zip(wildtrack_cameras, wildtrack_distorted_cameras, strict=True):
        assert camera.image_size == (1920, 1080)
        assert not camera.has_distortion and distorted.has_distortion
        np.testing.assert_allclose(camera.intrinsics, distorted.intrinsics)
        # Centimetres in the files, metres here: the cameras stand a few metres up.
        assert 1.0 < camera.centre[2] < 20.0
        assert np.all(np.abs(camera.centre[:2]) < 50.0)


def test_wildtrack_extrinsic_files_hold_bare_text(wildtrack_root):
    path = wildtrack_root / "calibrations/extrinsic/extr_CVLab1.xml"
    assert "opencv-matrix" not in path.read_text()
    values = read_opencv_matrices(path, ("rvec", "tvec"))
    assert values["rvec"].shape == (3,) and values["tvec"].shape == (3,)


def test_bare_rvec_tvec_text_xml(tmp_path):
    camera = posed_camera()
    rvec = cv2.Rodrigues(camera.rotation)[0].ravel()
    extrinsic = tmp_path / "extr.xml"
    extrinsic.write_text(
        '<?xml version="1.0"?>\n<opencv_storage>\n'
        f"<rvec>{' '.join(str(float(v)) for v in rvec)}</rvec>\n"
        f"<tvec>{' '.join(str(float(v) * 100) for v in camera.translation)}</tvec>\n"
        "</opencv_storage>\n"
    )
    intrinsic = tmp_path / "intr.xml"
    storage = cv2.FileStorage(str(intrinsic), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", camera.intrinsics)
    storage.release()
    read = read_opencv_camera("c", intrinsic, extrinsic, (640, 360), unit_to_metres=0.01)
    assert_same_geometry(read, camera)


@pytest.mark.parametrize("suffix", [".xml", ".yml"])
@pytest.mark.parametrize("with_distortion", [False, True])
def test_opencv_filestorage_matrices(tmp_path, suffix, with_distortion):
    distortion = np.array([-0.2, 0.05, 0.001, -0.002, 0.0]) if with_distortion else None
    camera = posed_camera(distortion=distortion)
    intrinsic, extrinsic = tmp_path / f"intr{suffix}", tmp_path / f"extr{suffix}"
    storage = cv2.FileStorage(str(intrinsic), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", camera.intrinsics)
    if distortion is not None:
        storage.write("distortion_coefficients", distortion.reshape(5, 1))
    storage.release()
    storage = cv2.FileStorage(str(extrinsic), cv2.FILE_STORAGE_WRITE)
    storage.write("rvec", cv2.Rodrigues(camera.rotation)[0])
    storage.write("tvec", camera.translation.reshape(3, 1))
    storage.release()
    read = read_opencv_camera("c", intrinsic, extrinsic, (640, 360))
    assert read.has_distortion == with_distortion
    np.testing.assert_allclose(read.distortion, camera.distortion)
    assert_same_geometry(read, camera)
    ignored = read_opencv_camera("c", intrinsic, extrinsic, (640, 360), use_distortion=False)
    assert not ignored.has_distortion


@pytest.mark.parametrize(
    ("intrinsic_text", "extrinsic_text", "message"),
    [
        ("<opencv_storage></opencv_storage>", "<rvec>0 0 0</rvec>", "has no camera_matrix"),
        (
            "<opencv_storage><camera_matrix>1 0 0 0 1 0 0 0</camera_matrix></opencv_storage>",
            "<opencv_storage><rvec>0 0 0</rvec><tvec>0 0 1</tvec></opencv_storage>",
            "camera_matrix must be 3x3, got 8 values",
        ),
        (
            "<opencv_storage><camera_matrix>1 0 0 0 1 0 0 0 1</camera_matrix></opencv_storage>",
            "<opencv_storage><rvec>0 0 0</rvec></opencv_storage>",
            "has no tvec",
        ),
        (
            "<opencv_storage><camera_matrix>1 0 0 0 1 0 0 0 1</camera_matrix></opencv_storage>",
            "<opencv_storage><rvec>0 zero 0</rvec><tvec>0 0 1</tvec></opencv_storage>",
            "rvec holds non-numeric values",
        ),
        (
            "<opencv_storage><camera_matrix>1 0 0 0 1 0 0 0 1</camera_matrix></opencv_storage>",
            "<opencv_storage><rvec>0 0</rvec><tvec>0 0 1</tvec></opencv_storage>",
            "rvec and tvec must have 3 values each",
        ),
        ("<opencv_storage><camera_matrix>", "<rvec>0 0 0</rvec>", "is not valid XML"),
        (
            "<opencv_storage><camera_matrix>1 0 0 0 1 0 0 0 1</camera_matrix></opencv_storage>",
            '<?xml version="1.0"?>\n<opencv_storage><rvec>np.float64(1.7) 0 0</rvec>'
            "<tvec>0 0 1</tvec></opencv_storage>",
            "rvec holds non-numeric values",
        ),
    ],
)
def test_bad_opencv_files(tmp_path, intrinsic_text, extrinsic_text, message):
    intrinsic, extrinsic = tmp_path / "intr.xml", tmp_path / "extr.xml"
    intrinsic.write_text(intrinsic_text)
    extrinsic.write_text(extrinsic_text)
    with pytest.raises(CalibrationError, match=message):
        read_opencv_camera("c", intrinsic, extrinsic, (640, 360))


def test_missing_calibration_file(tmp_path):
    with pytest.raises(CalibrationError, match="does not exist"):
        read_opencv_matrices(tmp_path / "nothing.xml", ("rvec",))


# ---------------------------------------------------------------------- AI City
def aicity_data(camera: Camera, projection: bool) -> dict:
    data = {"homography matrix": (camera.homography / camera.homography[2, 2]).tolist()}
    if projection:
        matrix = camera.intrinsics @ np.column_stack([camera.rotation, camera.translation])
        data["camera projection matrix"] = (-matrix / 3.0).tolist()  # any scale and sign
    return data


@pytest.mark.parametrize("projection", [False, True])
def test_aicity_calibration(tmp_path, projection):
    camera = posed_camera()
    folder = tmp_path / "c005"
    folder.mkdir()
    path = folder / "calibration.json"
    path.write_text(json.dumps({**aicity_data(camera, projection), "image_size": [640, 360]}))
    read = read_aicity_calibration(path)
    assert read.name == "c005"
    assert read.has_pose == projection
    assert_same_geometry(read, camera)
    if projection:
        np.testing.assert_allclose(read.centre, camera.centre, atol=1e-9)
        # Planes above the ground work with the projection matrix.
        world_xy, valid = read.pixel_to_world(PIXELS, 1.0)
        expected, _ = camera.pixel_to_world(PIXELS, 1.0)
        np.testing.assert_allclose(world_xy[valid], expected[valid], atol=1e-6)


def test_aicity_homography_and_projection_agree(tmp_path):
    camera = posed_camera()
    paths = {}
    for projection in (False, True):
        paths[projection] = tmp_path / f"{projection}.json"
        data = {**aicity_data(camera, projection), "image_size": [640, 360]}
        paths[projection].write_text(json.dumps(data))
    assert_same_geometry(
        read_aicity_calibration(paths[False]), read_aicity_calibration(paths[True])
    )


def test_aicity_scene_folder(tmp_path):
    camera = posed_camera()
    for name in ("c002", "c001"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "calibration.json").write_text(json.dumps(aicity_data(camera, False)))
    cameras = read_cameras(tmp_path)
    assert [camera.name for camera in cameras] == ["c001", "c002"]
    assert cameras[0].image_size == (1920, 1080)  # the AI City default
    assert calibration_layout(tmp_path) == "aicity"
    assert default_ground(tmp_path) is None


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({}, "has neither 'homography matrix' nor 'camera projection matrix'"),
        ({"homography matrix": [[1, 0], [0, 1]]}, r"must be 3x3, got shape \(2, 2\)"),
        ({"homography matrix": [[1, 0, 0], [0, 1]]}, "must be a 3x3 matrix of numbers"),
        ({"homography matrix": [[0, 0, 0]] * 3}, "the homography is singular"),
        ({"camera projection matrix": [[1, 0, 0]] * 3}, r"must be 3x4, got shape \(3, 3\)"),
        ({"camera projection matrix": [[0, 0, 0, 1]] * 3}, "projection matrix is singular"),
        ([1, 2, 3], "must be a JSON object"),
    ],
)
def test_bad_aicity_files(tmp_path, data, message):
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=message):
        read_aicity_calibration(path)


# ---------------------------------------------------------------------- cblrs JSON
def test_cblrs_json_three_forms(tmp_path):
    camera = posed_camera(distortion=np.array([-0.1, 0.01, 0.0, 0.0, 0.0]))
    full = camera_to_dict(camera)
    homography_only = camera_to_dict(Camera.from_homography("h", camera.homography, (640, 360)))
    pose = {
        "name": "p",
        "image_size": [640, 360],
        "position": [0.0, -12.0, 6.0],
        "pan_deg": 90.0,
        "tilt_deg": 12.0,
        "focal_px": 500.0,
    }
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"cameras": [full, homography_only, pose]}))
    cameras = read_cameras(path)
    assert [c.name for c in cameras] == ["synthetic", "h", "p"]
    assert cameras[0].has_distortion and "homography" not in full
    assert set(homography_only) == {"name", "image_size", "homography"}
    assert_same_geometry(cameras[0], camera)
    pinhole = posed_camera()
    assert_same_geometry(cameras[1], pinhole)
    assert_same_geometry(cameras[2], pinhole)
    # One camera per file works too.
    single = tmp_path / "single.json"
    single.write_text(json.dumps(pose))
    assert [c.name for c in read_camera_json(single)] == ["p"]
    assert calibration_layout(single) == "json"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "is not valid JSON"),
        ("[]", r"expected a camera object or \{'cameras': \[...\]\}"),
        ('{"cameras": [3]}', "each camera must be a JSON object"),
        ('{"name": "a", "image_size": [10, 10]}', "needs 'homography', 'intrinsics' or 'position'"),
        ('{"name": "a"}', "invalid camera entry"),
        (
            '{"name": "a", "image_size": [10, 10], "intrinsics": [[1,0,0],[0,1,0],[0,0,1]]}',
            "needs rvec/rotation and tvec",
        ),
        ('{"name": "a", "image_size": [10, 10], "position": [0, 0, 5]}', "invalid camera entry"),
    ],
)
def test_bad_cblrs_json(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(CalibrationError, match=message):
        read_cameras(path)


# ---------------------------------------------------------------------- auto-detection
def test_multiviewx_layout(tmp_path):
    camera = posed_camera()
    (tmp_path / "calibrations/intrinsic").mkdir(parents=True)
    (tmp_path / "calibrations/extrinsic").mkdir(parents=True)
    for index in (2, 1, 10):
        storage = cv2.FileStorage(
            str(tmp_path / f"calibrations/intrinsic/intr_Camera{index}.xml"),
            cv2.FILE_STORAGE_WRITE,
        )
        storage.write("camera_matrix", camera.intrinsics)
        storage.write("distortion_coefficients", np.zeros((5, 1)))
        storage.release()
        rvec = " ".join(str(float(v)) for v in cv2.Rodrigues(camera.rotation)[0].ravel())
        tvec = " ".join(str(float(v)) for v in camera.translation)
        (tmp_path / f"calibrations/extrinsic/extr_Camera{index}.xml").write_text(
            f"<opencv_storage><rvec>{rvec}</rvec><tvec>{tvec}</tvec></opencv_storage>"
        )
    cameras = read_cameras(tmp_path)
    assert [c.name for c in cameras] == ["Camera1", "Camera2", "Camera10"]
    assert calibration_layout(tmp_path) == "multiviewx"
    assert default_ground(tmp_path) == MULTIVIEWX_GROUND
    world_xy, valid = cameras[0].pixel_to_world(PIXELS)
    expected, _ = camera.pixel_to_world(PIXELS)
    np.testing.assert_allclose(world_xy[valid], expected[valid], atol=1e-6)


def test_wildtrack_layout_detection(wildtrack_root):
    assert calibration_layout(wildtrack_root) == "wildtrack"
    assert default_ground(wildtrack_root) == WILDTRACK_GROUND
    assert len(read_cameras(wildtrack_root)) == 7
    assert all(camera.has_distortion for camera in read_cameras(wildtrack_root, distorted=True))


@pytest.mark.parametrize("make", ["empty folder", "missing path"])
def test_unknown_calibration_paths(tmp_path, make):
    path = tmp_path if make == "empty folder" else tmp_path / "nothing.json"
    message = (
        "is not a WILDTRACK, MultiviewX or AI City folder"
        if make == "empty folder"
        else ("does not exist")
    )
    with pytest.raises(CalibrationError, match=message):
        read_cameras(path)
