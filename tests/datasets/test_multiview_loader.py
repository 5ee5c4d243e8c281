"""load_scene on a fake MultiviewX folder (built here) and on the real WILDTRACK data."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs.calibration import WILDTRACK_GROUND
from cblrs.datasets import Scene, load_scene
from cblrs.datasets.multiview import GROUND_MARGIN_M, detect_layout, position_to_world
from cblrs.errors import CblrsError, DatasetError

CAMERA_COUNT = 3


def write_multiviewx_camera(root: Path, number: int) -> None:
    """Camera<number> 10 m above the plane's centre looking down-ish, as OpenCV XML files."""
    intrinsic = root / "calibrations" / "intrinsic"
    extrinsic = root / "calibrations" / "extrinsic"
    intrinsic.mkdir(parents=True, exist_ok=True)
    extrinsic.mkdir(parents=True, exist_ok=True)
    storage = cv2.FileStorage(str(intrinsic / f"intr_Camera{number}.xml"), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]))
    storage.write("distortion_coefficients", np.array([[0.01, -0.02, 0.0, 0.0, 0.003]]))
    storage.release()
    storage = cv2.FileStorage(str(extrinsic / f"extr_Camera{number}.xml"), cv2.FILE_STORAGE_WRITE)
    # Rotation of pi about x: camera looks straight down at the ground; t in metres.
    storage.write("rvec", np.array([[np.pi], [0.0], [0.0]]))
    storage.write("tvec", np.array([[-12.5 + number], [8.0], [10.0]]))
    storage.release()


def person(person_id: int, position_id: int, boxes: dict[int, list[float]]) -> dict:
    views = []
    for view in range(CAMERA_COUNT):
        x_min, y_min, x_max, y_max = boxes.get(view, [-1, -1, -1, -1])
        views.append({"viewNum": view, "xmin": x_min, "ymin": y_min, "xmax": x_max, "ymax": y_max})
    return {"personID": person_id, "positionID": position_id, "views": views}


@pytest.fixture()
def multiviewx_root(tmp_path: Path) -> Path:
    root = tmp_path / "MultiviewX"
    # Written out of order on purpose: the cameras must come back in view order.
    for number in (2, 1, 3):
        write_multiviewx_camera(root, number)
    annotations = root / "annotations_positions"
    annotations.mkdir()
    frames = {
        0: [person(7, 123_456, {0: [10, 20, 50, 120], 2: [-5, 900, 40, 1100]})],
        1: [person(7, 123_457, {1: [100, 200, 150, 300]}), person(9, 0, {})],
        2: [],
    }
    for frame, people in frames.items():
        (annotations / f"{frame:05d}.json").write_text(json.dumps(people))
    return root


def test_multiviewx_cameras_in_view_order(multiviewx_root: Path) -> None:
    scene = load_scene(multiviewx_root)
    assert isinstance(scene, Scene)
    assert detect_layout(multiviewx_root) == "multiviewx"
    assert scene.camera_names == ["Camera1", "Camera2", "Camera3"]
    # Camera k's centre is at x = -(-12.5 + k) after the rotation by pi about x.
    centres = np.array([camera.centre for camera in scene.cameras])
    np.testing.assert_allclose(centres[:, 0], [11.5, 10.5, 9.5], atol=1e-9)
    np.testing.assert_allclose(centres[:, 2], [10.0] * 3, atol=1e-9)
    # The calibration is used as given: distortion kept.
    np.testing.assert_allclose(scene.cameras[0].distortion, [0.01, -0.02, 0.0, 0.0, 0.003])
    assert not np.any(load_scene(multiviewx_root, distorted=False).cameras[0].distortion)


def test_multiviewx_frames_timestamps_and_positions(multiviewx_root: Path) -> None:
    scene = load_scene(multiviewx_root)
    np.testing.assert_array_equal(scene.frames, [0, 1, 2])
    np.testing.assert_allclose(scene.timestamps, [0.0, 0.5, 1.0])  # 2 fps
    assert scene.frame_interval == pytest.approx(0.5)
    truth = scene.ground_truth
    np.testing.assert_array_equal(truth.frame, [0, 1, 1])
    np.testing.assert_array_equal(truth.track_id, [7, 7, 9])
    np.testing.assert_allclose(truth.timestamp, [0.0, 0.5, 0.5])
    np.testing.assert_array_equal(truth.camera_id, [-1, -1, -1])
    # positionID 123456: x = 456 / 40 = 11.4 m, y = 123 / 40 = 3.075 m.
    np.testing.assert_allclose(truth.world_xy, [[11.4, 3.075], [11.425, 3.075], [0.0, 0.0]])
    # The annotated area (0, 0, 25 x 16 m) grown by the margin on every side.
    margin = GROUND_MARGIN_M
    assert margin > 0
    assert scene.plane.origin == (-margin, -margin)
    assert (scene.plane.width, scene.plane.length, scene.plane.bits) == (
        25.0 + 2 * margin, 16.0 + 2 * margin, 16,
    )
    assert scene.plane.step[0] < 1e-3  # still sub-millimetre at 16 bits


def test_multiviewx_detections_per_camera(multiviewx_root: Path) -> None:
    scene = load_scene(multiviewx_root)
    counts = [[len(detections) for detections in frame] for frame in scene.detections]
    assert counts == [[1, 0, 1], [0, 1, 0], [0, 0, 0]]
    boxes = scene.detections[0][2]
    # Boxes reaching outside the image are kept as annotated.
    np.testing.assert_allclose(boxes.xyxy, [[-5, 900, 40, 1100]])
    np.testing.assert_array_equal(boxes.object_id, [7])
    np.testing.assert_array_equal(boxes.class_id, [0])
    np.testing.assert_array_equal(boxes.confidence, [1.0])


@pytest.mark.parametrize(
    ("position_id", "layout", "expected"),
    [
        (0, "multiviewx", [0.0, 0.0]),
        (999, "multiviewx", [24.975, 0.0]),
        (639_999, "multiviewx", [24.975, 15.975]),
        (0, "wildtrack", [-3.0, -9.0]),
        (481, "wildtrack", [-2.975, -8.975]),
    ],
)
def test_position_to_world(position_id: int, layout: str, expected: list[float]) -> None:
    np.testing.assert_allclose(position_to_world(np.array([position_id]), layout), [expected])


def test_position_to_world_empty() -> None:
    assert position_to_world(np.zeros(0, np.int64), "wildtrack").shape == (0, 2)


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        load_scene(tmp_path / "nowhere")


def test_unknown_layout(tmp_path: Path, multiviewx_root: Path) -> None:
    with pytest.raises(DatasetError, match="neither a WILDTRACK layout"):
        load_scene(tmp_path)
    with pytest.raises(DatasetError, match="unknown dataset layout 'mot17'"):
        load_scene(multiviewx_root, layout="mot17")


def test_no_annotation_files(multiviewx_root: Path) -> None:
    for file in (multiviewx_root / "annotations_positions").glob("*.json"):
        file.unlink()
    with pytest.raises(DatasetError, match="holds no annotation files"):
        load_scene(multiviewx_root)
    (multiviewx_root / "annotations_positions").rmdir()
    with pytest.raises(DatasetError, match="has no annotations_positions/ folder"):
        load_scene(multiviewx_root)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("[{", "00001.json is not valid JSON"),
        ('{"personID": 1}', "00001.json must hold a JSON list"),
        ('[{"personID": 1}]', "00001.json: entry 0 is malformed"),
        ('[{"personID": 1, "positionID": 2, "views": [{"viewNum": 0}]}]', "entry 0 is malformed"),
        (
            '[{"personID": 1, "positionID": 2, "views": '
            '[{"viewNum": 9, "xmin": 1, "ymin": 1, "xmax": 2, "ymax": 2}]}]',
            "viewNum 9 of personID 1 is not one of the 3 cameras",
        ),
    ],
)
def test_malformed_annotation_names_the_file(
    multiviewx_root: Path, content: str, message: str
) -> None:
    (multiviewx_root / "annotations_positions" / "00001.json").write_text(content)
    with pytest.raises(DatasetError, match=message):
        load_scene(multiviewx_root)


def test_numbers_written_otherwise_load_alike(multiviewx_root: Path) -> None:
    # Integers and numbers as JSON expects them take msgspec's typed decoder; a file writing
    # them as strings or 7.0 takes the general path, which converts them the same way.
    expected = load_scene(multiviewx_root)
    (multiviewx_root / "annotations_positions" / "00000.json").write_text(json.dumps([{
        "personID": "7", "positionID": 123456.0, "note": "extra keys are ignored",
        "views": [{"viewNum": 0, "xmin": "10", "ymin": 20, "xmax": 50.0, "ymax": "120"},
                  {"viewNum": 2.0, "xmin": -5, "ymin": 900, "xmax": 40, "ymax": 1100}],
    }]))
    scene = load_scene(multiviewx_root)
    for got, want in zip(scene.detections[0], expected.detections[0], strict=True):
        np.testing.assert_array_equal(got.xyxy, want.xyxy)
        np.testing.assert_array_equal(got.object_id, want.object_id)
    np.testing.assert_array_equal(scene.ground_truth.world_xy, expected.ground_truth.world_xy)
    np.testing.assert_array_equal(scene.ground_truth.track_id, expected.ground_truth.track_id)


def test_missing_calibration_is_a_clear_error(multiviewx_root: Path) -> None:
    (multiviewx_root / "calibrations" / "extrinsic" / "extr_Camera2.xml").unlink()
    with pytest.raises(CblrsError, match=r"extr_Camera2\.xml does not exist"):
        load_scene(multiviewx_root)


def test_wildtrack(wildtrack_root: Path) -> None:
    scene = load_scene(wildtrack_root)
    assert detect_layout(wildtrack_root) == "wildtrack"
    assert scene.camera_names == [
        "CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3",
    ]
    assert scene.frames[0] == 0 and np.all(np.diff(scene.frames) == 5)
    np.testing.assert_allclose(scene.timestamps, scene.frames / 10.0)
    assert scene.frame_interval == pytest.approx(0.5)
    # Annotations are on undistorted frames, so the default has no distortion.
    assert not any(np.any(camera.distortion) for camera in scene.cameras)
    distorted = load_scene(wildtrack_root, distorted=True)
    assert any(np.any(camera.distortion) for camera in distorted.cameras)
    # First person of 00000000.json: personID 122, positionID 456826.
    truth = scene.ground_truth
    first = truth[(truth.frame == 0) & (truth.track_id == 122)]
    expected = [-3.0 + 0.025 * (456826 % 480), -9.0 + 0.025 * (456826 // 480)]
    np.testing.assert_allclose(first.world_xy, [expected])
    # The plane is the annotated area grown by the margin on every side.
    x0, y0, width, length = WILDTRACK_GROUND
    assert scene.plane.origin == (x0 - GROUND_MARGIN_M, y0 - GROUND_MARGIN_M)
    assert scene.plane.width == pytest.approx(width + 2 * GROUND_MARGIN_M)
    assert scene.plane.length == pytest.approx(length + 2 * GROUND_MARGIN_M)
    assert scene.plane.contains(truth.world_xy).all()
    boxes = scene.detections[0][0]
    np.testing.assert_allclose(boxes.xyxy[boxes.object_id == 122], [[1510, 139, 1561, 299]])
    # Frame 85, view 3, person 4 has xmin = -1 (partly outside): kept, not skipped.
    index = int(np.flatnonzero(scene.frames == 85)[0])
    partial = scene.detections[index][3]
    np.testing.assert_allclose(partial.xyxy[partial.object_id == 4], [[-1, 239, 156, 686]])
    # Every detection's foot point is near its person's projected ground position.
    camera = scene.cameras[0]
    truth = scene.ground_truth[scene.ground_truth.frame == 0]
    positions = {int(i): xy for i, xy in zip(truth.track_id, truth.world_xy, strict=True)}
    pixels, _ = camera.world_to_pixel(np.array([positions[int(i)] for i in boxes.object_id]))
    feet = np.stack([(boxes.xyxy[:, 0] + boxes.xyxy[:, 2]) / 2, boxes.xyxy[:, 3]], axis=1)
    assert np.median(np.linalg.norm(pixels - feet, axis=1)) < 20.0


@pytest.mark.parametrize(
    ("name", "make", "problem"),
    [
        ("whole.jpg", lambda jpeg, png: jpeg, None),
        ("padded.jpg", lambda jpeg, png: jpeg + b"\x00\x00\n", None),
        ("cut.jpg", lambda jpeg, png: jpeg[: len(jpeg) // 2], "truncated"),
        ("empty.jpg", lambda jpeg, png: b"", "empty"),
        ("whole.png", lambda jpeg, png: png, None),
        ("cut.png", lambda jpeg, png: png[:-20], "truncated"),
    ],
)
def test_image_problems_are_found_from_the_file_ends(tmp_path, name, make, problem):
    import cv2

    from cblrs.datasets.images import UnusableImage, image_problem, read_image

    picture = np.random.default_rng(0).integers(0, 255, (64, 80, 3), dtype=np.uint8)
    jpeg = cv2.imencode(".jpg", picture)[1].tobytes()
    png = cv2.imencode(".png", picture)[1].tobytes()
    path = tmp_path / name
    path.write_bytes(make(jpeg, png))
    assert image_problem(path) == problem
    if problem is None:
        assert read_image(path).shape == (64, 80, 3)
    else:
        with pytest.raises(UnusableImage) as caught:
            read_image(path)
        assert caught.value.reason == problem and str(path) in str(caught.value)
