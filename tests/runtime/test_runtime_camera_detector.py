"""``cblrs camera`` with the ONNX detector on real frames, and sources that end early."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets import load_scene
from cblrs.detectors import ColourBlobDetector
from cblrs.errors import DatasetError
from cblrs.pipeline import render_scene_references
from cblrs.runtime.camera.sources import image_folder_source, video_source


@pytest.fixture(scope="module")
def camera1_reference(multiviewx_real_root, tmp_path_factory) -> Path:
    scene = load_scene(multiviewx_real_root)
    path = tmp_path_factory.mktemp("references") / "Camera1.png"
    render_scene_references(scene)[0].save(path)
    return path


def _clip(path: Path, frames: int) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
    for index in range(frames):
        image = np.zeros((240, 320, 3), np.uint8)
        image[100:140, 50 + 10 * index : 70 + 10 * index] = (0, 0, 255)
        writer.write(image)
    writer.release()
    return path


def test_video_frames_first_to_last(tmp_path):
    detector = ColourBlobDetector((255, 0, 0), tolerance=60, min_area=50)
    frames = list(video_source(_clip(tmp_path / "clip.avi", 6), detector, first=2, last=4))
    assert [frame.frame for frame in frames] == [2, 3, 4]


def test_a_video_that_ends_early_is_an_error(tmp_path):
    detector = ColourBlobDetector((255, 0, 0), tolerance=60, min_area=50)
    frames = []
    with pytest.raises(DatasetError, match="ended after 3 frames, before the requested last"):
        for frame in video_source(_clip(tmp_path / "clip.avi", 3), detector, last=9):
            frames.append(frame)
    assert len(frames) == 3  # the frames it had were delivered


def test_an_image_folder_shorter_than_requested_is_an_error(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for index in range(2):
        cv2.imwrite(str(folder / f"{index:04d}.png"), np.zeros((20, 20, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"holds 2 images .* fewer than the requested last"):
        list(image_folder_source(folder, ColourBlobDetector((1, 2, 3)), 2.0, last=5))


def test_camera_command_skips_unusable_images(multiviewx_real_root, yolox_model,
                                              camera1_reference, mosquitto, tmp_path, capsys,
                                              caplog):
    # Issue 21: a zero-byte image ended the camera's run; a JPEG cut short was detected on
    # silently. Both frames are now skipped (no message: an empty one would claim nobody was
    # there), counted by reason and said; the other frames are sent.
    folder = tmp_path / "C1"
    folder.mkdir()
    source = multiviewx_real_root / "Image_subsets" / "C1"
    for index in range(4):
        (folder / f"{index:04d}.jpg").write_bytes((source / f"{index:04d}.jpg").read_bytes())
    (folder / "0001.jpg").write_bytes(b"")
    whole = (folder / "0002.jpg").read_bytes()
    (folder / "0002.jpg").write_bytes(whole[: 2 * len(whole) // 3])
    code = main([
        "camera", "--camera", "Camera1", "--reference", str(camera1_reference),
        "--images", str(folder), "--fps", "2", "--detector", "onnx", "--model", str(yolox_model),
        "--tiling", "off", "--epoch", str(time.time()), "--broker",
        f"127.0.0.1:{mosquitto.port}", "--json", "--confirm-timeout", "0",
        "--spool", str(tmp_path / "spool.db"),
    ])
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert code == 0, captured.err
    assert report["frames"] == 4 and report["messages"] == 2 and report["flushed"]
    assert report["frames_skipped"] == {"empty": 1, "truncated": 1}
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert (f"camera Camera1: image skipped (1 so far): image {folder / '0001.jpg'} is empty "
            "(0 bytes).") in warnings
    assert any(f"image skipped (2 so far): image {folder / '0002.jpg'} is cut short" in line
               for line in warnings)
    # Without --json the summary line says it too.
    code = main([
        "camera", "--camera", "Camera1", "--reference", str(camera1_reference),
        "--images", str(folder), "--fps", "2", "--detector", "onnx", "--model", str(yolox_model),
        "--tiling", "off", "--epoch", str(time.time()), "--broker",
        f"127.0.0.1:{mosquitto.port}", "--confirm-timeout", "0",
        "--spool", str(tmp_path / "spool2.db"),
    ])
    assert code == 0
    assert "(frames skipped, unusable image: 1 empty, 1 truncated)" in capsys.readouterr().out


def test_camera_command_detects_on_real_frames(
    multiviewx_real_root, yolox_model, camera1_reference, mosquitto, capsys
):
    code = main([
        "camera", "--camera", "Camera1", "--reference", str(camera1_reference),
        "--images", str(multiviewx_real_root / "Image_subsets" / "C1"), "--frames", "0:1",
        "--fps", "2", "--detector", "onnx", "--model", str(yolox_model),
        "--epoch", str(time.time()), "--broker", f"127.0.0.1:{mosquitto.port}", "--json",
        "--confirm-timeout", "0",  # no matcher here: the broker's acknowledgement is enough
    ])
    report = json.loads(capsys.readouterr().out)
    assert code == 0
    assert report["messages"] == 2 and report["flushed"]
    assert report["detections"] >= 15 and report["located"] >= 10


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--images", "IMAGES", "--detector", "onnx"], "--detector onnx needs --model"),
        (["--images", "IMAGES", "--detector", "onnx", "--model", "NOT_ONNX"],
         "is not an ONNX model"),
        (["--video", "CLIP", "--detector", "blob", "--frames", "0:9"],
         "ended after 3 frames, before the requested last frame 9"),
        (["--images", "BROKEN", "--detector", "blob"],
         "every one of the 1 frames had an unusable image (1 truncated): nothing was sent."),
    ],
)
def test_camera_command_input_mistakes(
    tmp_path, camera1_reference, mosquitto, capsys, arguments, message
):
    (tmp_path / "not.onnx").write_bytes(b"\x00\x01 nonsense")
    (tmp_path / "images").mkdir()
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "0000.jpg").write_bytes(b"\xff\xd8 not really")
    replacements = {
        "IMAGES": str(tmp_path / "images"),
        "NOT_ONNX": str(tmp_path / "not.onnx"),
        "CLIP": str(_clip(tmp_path / "clip.avi", 3)),
        "BROKEN": str(tmp_path / "broken"),
    }
    code = main([
        "camera", "--camera", "Camera1", "--reference", str(camera1_reference),
        "--fps", "10", "--epoch", str(time.time()), "--flush-timeout", "5",
        "--broker", f"127.0.0.1:{mosquitto.port}",
        *[replacements.get(item, item) for item in arguments],
    ])
    error = capsys.readouterr().err
    assert code != 0
    assert message in error, error
    sentences = [line for line in error.splitlines() if "cblrs camera: error:" in line]
    assert len(sentences) == 1 and "Traceback" not in error, error
