"""``cblrs track`` from real images through the shipped detector, and from detection files
(the acceptance run on every MultiviewX image is test_detectors_track_real_images.py)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_models import constant_model

from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks
from cblrs.datasets.detection_folder import read_detection_folder
from cblrs.errors import DatasetError
from cblrs.evaluation.metrics import evaluate


def _track(arguments: list[str], capsys) -> tuple[int, str, str]:
    code = main(["track", *arguments])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _write_mot_folder(scene, folder: Path, names: list[str], frame_shift: int = 0) -> Path:
    """The annotated boxes as a folder of per-camera MOT files (frame,id,x,y,w,h,conf)."""
    folder.mkdir(parents=True, exist_ok=True)
    for camera, name in enumerate(names):
        lines = []
        for position, frame in enumerate(scene.frames):
            boxes = scene.detections[position][camera]
            for (x0, y0, x1, y1), person in zip(boxes.xyxy, boxes.object_id, strict=True):
                lines.append(f"{frame + frame_shift},{person},{x0},{y0},{x1 - x0},{y1 - y0},1")
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_track_without_tiles_on_a_few_frames(multiviewx_real_root, yolox_model, tmp_path, capsys):
    out = tmp_path / "tracks.txt"
    code, stdout, _ = _track(
        [str(multiviewx_real_root), "--out", str(out), "--detector", "onnx", "--model",
         str(yolox_model), "--tiling", "off", "--frames", "1:3", "--json", "--quiet"], capsys,
    )
    assert code == 0
    summary = json.loads(stdout)
    assert summary["frames"] == 3 and summary["detections"] > 30
    assert set(summary["detector"]["tiles"].values()) == {"whole frame"}
    tracks = read_tracks(out)
    assert set(np.unique(tracks.frame).tolist()) <= {1, 2, 3} and len(tracks) > 20


def test_track_from_a_folder_of_detection_files(multiviewx_real_root, tmp_path, capsys):
    scene = load_scene(multiviewx_real_root)
    # Files named after the calibration cameras and after the image folders both work.
    folder = _write_mot_folder(
        scene, tmp_path / "dets", ["Camera1", "Camera2", "Camera3", "C4", "C5", "C6"]
    )
    out = tmp_path / "tracks.txt"
    code, stdout, _ = _track(
        [str(multiviewx_real_root), "--out", str(out), "--detections", str(folder),
         "--hidden-feet", "keep", "--json", "--quiet"], capsys,
    )
    assert code == 0 and json.loads(stdout)["source"] == "detections"
    metrics = evaluate(scene.ground_truth, read_tracks(out))
    assert metrics.HOTA >= 93.0


def test_a_camera_without_a_file_sees_nothing(multiviewx_real_root, tmp_path, caplog):
    scene = load_scene(multiviewx_real_root)
    folder = _write_mot_folder(scene, tmp_path / "dets", ["Camera1", "Camera2"])
    read = read_detection_folder(scene, folder)
    assert [len(d) for d in read.detections[0][2:]] == [0, 0, 0, 0]
    assert len(read.detections[0][0]) == len(scene.detections[0][0])
    assert "Camera3, Camera4, Camera5, Camera6" in caplog.text


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda scene, folder: _write_mot_folder(scene, folder, ["Camera1", "Camera9"]),
         r"detections file Camera9.txt names no camera of the data set \(cameras: Camera1, "),
        (lambda scene, folder: _write_mot_folder(scene, folder, ["Camera1", "C1"]),
         "both hold camera Camera1's detections"),
        (lambda scene, folder: _write_mot_folder(scene, folder, ["Camera1"], frame_shift=-1),
         "numbered like the image files .* add 1 to its frame numbers"),
        (lambda scene, folder: _write_mot_folder(scene, folder, ["Camera1"], frame_shift=500),
         "none of the data set's frames 1..10"),
        (lambda scene, folder: folder.mkdir(), "holds no detection files"),
    ],
)
def test_detection_folder_mistakes_are_one_sentence(
    multiviewx_real_root, tmp_path, capsys, setup, message
):
    scene = load_scene(multiviewx_real_root)
    folder = tmp_path / "dets"
    setup(scene, folder)
    with pytest.raises(DatasetError, match=message):
        read_detection_folder(scene, folder, dataset_root=multiviewx_real_root)
    code, _, error = _track(
        [str(multiviewx_real_root), "--out", str(tmp_path / "t.txt"), "--detections",
         str(folder), "--quiet"], capsys,
    )
    assert code == 1 and re.search(message, error) and error.count("\n") == 1


def _dataset_copy(root: Path, tmp_path: Path) -> Path:
    """A scratch copy of the MultiviewX folder (for breaking one of its images)."""
    copy = tmp_path / "multiviewx"
    shutil.copytree(root, copy)
    return copy


@pytest.mark.parametrize(
    ("arguments", "message", "code"),
    [
        (["--detector", "onnx"], "--detector onnx needs --model MODEL.onnx", 2),
        (["--model", "M.onnx"], "--model needs --detector onnx", 2),
        (["--detector", "onnx", "--model", "NOT_ONNX"], "is not an ONNX model", 1),
        (["--detector", "onnx", "--model", "CLASSIFIER"],
         "expected a YOLO detection output", 1),
        (["--detector", "onnx", "--model", "MODEL", "--detections", "D"],
         "either --detector or --detections", 2),
        (["--detector", "onnx", "--model", "MODEL", "--drop", "0.2"],
         "simulate a detector on the annotated boxes", 2),
        (["--detector", "onnx", "--model", "MODEL", "--confidence", "2"],
         "--confidence must be within 0..1", 2),
    ],
)
def test_detector_option_mistakes(
    multiviewx_real_root, yolox_model, tmp_path, capsys, arguments, message, code
):
    (tmp_path / "not.onnx").write_text("hello")
    constant_model(tmp_path / "classifier.onnx", np.zeros((1, 1000), np.float32))
    replacements = {
        "NOT_ONNX": str(tmp_path / "not.onnx"),
        "CLASSIFIER": str(tmp_path / "classifier.onnx"),
        "MODEL": str(yolox_model),
        "D": str(tmp_path),
    }
    arguments = [replacements.get(item, item) for item in arguments]
    result, _, error = _track(
        [str(multiviewx_real_root), "--out", str(tmp_path / "t.txt"), "--quiet", *arguments],
        capsys,
    )
    assert result == code
    assert message in error and error.count("\n") == 1


def test_unusable_images_are_skipped_counted_and_said(multiviewx_real_root, yolox_model,
                                                      tmp_path, capsys, caplog):
    # Issue 21: one zero-byte image aborted the whole run, and a JPEG cut short was detected
    # on silently (OpenCV greys what is missing). Both are now skipped, counted and said.
    copy = _dataset_copy(multiviewx_real_root, tmp_path)
    empty = copy / "Image_subsets" / "C3" / "0001.jpg"
    empty.write_bytes(b"")
    cut = copy / "Image_subsets" / "C1" / "0002.jpg"
    whole = cut.read_bytes()
    cut.write_bytes(whole[: len(whole) // 2])
    garbage = copy / "Image_subsets" / "C2" / "0001.jpg"
    garbage.write_bytes(b"\xff\xd8 not a JPEG at all \xff\xd9")
    code, out, error = _track(
        [str(copy), "--out", str(tmp_path / "t.txt"), "--detector", "onnx", "--model",
         str(yolox_model), "--tiling", "off", "--frames", "1:3", "--json", "--quiet"], capsys,
    )
    assert code == 0, error
    summary = json.loads(out)
    assert summary["detector"]["images_skipped"] == {"empty": 1, "truncated": 1,
                                                     "undecodable": 1}
    assert summary["detector"]["images"] == 3 * 6 - 3
    said = caplog.text
    assert f"image {empty} is empty (0 bytes)." in said
    assert f"image {cut} is cut short" in said
    assert f"cannot read image {garbage}: not an image file OpenCV can decode." in said
    assert "image skipped (3 so far)" in said
    tracks = read_tracks(tmp_path / "t.txt")
    assert set(np.unique(tracks.frame).tolist()) == {1, 2, 3}
    # Every image unusable: one sentence, exit 1.
    for folder in (copy / "Image_subsets").iterdir():
        for image in folder.iterdir():
            image.write_bytes(b"")
    code, _, error = _track(
        [str(copy), "--out", str(tmp_path / "t.txt"), "--detector", "onnx", "--model",
         str(yolox_model), "--frames", "1:1", "--quiet"], capsys,
    )
    assert code == 1 and f"every one of the 6 images of {copy} is unusable (6 empty)." in error
    broken = copy / "Image_subsets" / "C3" / "0001.jpg"
    # A missing image is named too.
    broken.unlink()
    code, _, error = _track(
        [str(copy), "--out", str(tmp_path / "t.txt"), "--detector", "onnx", "--model",
         str(yolox_model), "--quiet"], capsys,
    )
    assert code == 1 and "has no image for annotated frame 2 (expected one numbered 1" in error


def test_images_of_the_wrong_size_are_refused(multiviewx_real_root, yolox_model, tmp_path, capsys):
    copy = _dataset_copy(multiviewx_real_root, tmp_path)
    path = copy / "Image_subsets" / "C1" / "0000.jpg"
    cv2.imwrite(str(path), np.zeros((540, 960, 3), np.uint8))
    code, _, error = _track(
        [str(copy), "--out", str(tmp_path / "t.txt"), "--detector", "onnx", "--model",
         str(yolox_model), "--frames", "1:1", "--quiet"], capsys,
    )
    assert code == 1 and "is 960x540 but camera Camera1 is calibrated for 1920x1080" in error
