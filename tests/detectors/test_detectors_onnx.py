"""The ONNX detector adapter: layouts, letterboxing, classes, NMS, bad models.

The YOLOv5 / v8 layouts are tested on small real ONNX models built here (see
``onnx_models``: no Ultralytics export can be downloaded); the YOLOX layout on such a model
and on the shipped YOLOX-Nano with real MultiviewX frames.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from onnx_models import COCO_COUNT, constant_model, grid_cells, v5_table, v8_table

from cblrs.datasets import load_scene
from cblrs.datasets.images import read_image, scene_image_paths
from cblrs.detections import CLASS_NAMES
from cblrs.detectors import (
    COCO_CLASS_NAMES,
    ModelError,
    OnnxDetector,
    box_iou,
    class_map,
    letterbox,
    non_maximum_suppression,
)

PERSON, CAR, BUS, BENCH = 0, 2, 5, 13


def _image(width: int, height: int) -> np.ndarray:
    return np.full((height, width, 3), 90, np.uint8)


def _xyxy(cx, cy, w, h, scale):
    return np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]) / scale


def test_coco_classes_map_to_cblrs_classes():
    mapping = class_map(COCO_CLASS_NAMES)
    expected = {"person": 0, "bicycle": 1, "car": 2, "motorcycle": 3, "bus": 5, "truck": 7}
    for name, coco_index in expected.items():
        assert mapping[coco_index] == CLASS_NAMES.index(name)
    assert (mapping >= 0).sum() == 6
    assert mapping[BENCH] == -1


def test_letterbox_keeps_the_aspect_and_pads_bottom_right():
    image = np.full((160, 320, 3), 7, np.uint8)
    canvas, scale = letterbox(image, (128, 96))
    assert canvas.shape == (96, 128, 3) and scale == pytest.approx(0.4)
    assert (canvas[:64] == 7).all() and (canvas[64:] == 114).all()


def test_yolov8_layout_decodes_known_boxes(tmp_path: Path):
    boxes = [
        (40, 30, 20, 40, PERSON, 0.9),
        (90, 50, 30, 20, CAR, 0.8),
        (60, 70, 10, 10, BENCH, 0.95),  # not a cblrs class
        (20, 20, 10, 20, PERSON, 0.2),  # below the confidence threshold
        (41, 31, 20, 40, PERSON, 0.6),  # the first person again: NMS drops it
        (41, 31, 20, 40, BUS, 0.5),  # same place, other class: kept
    ]
    model = constant_model(tmp_path / "v8.onnx", v8_table(boxes))
    detector = OnnxDetector(model)
    assert detector.layout == "yolov8" and detector.input_size == (128, 96)
    detections = detector.detect(_image(320, 160))  # letterbox scale 0.4
    assert len(detections) == 3
    order = np.argsort(-detections.confidence)
    np.testing.assert_allclose(detections.confidence[order], [0.9, 0.8, 0.5], atol=1e-6)
    np.testing.assert_array_equal(
        detections.class_id[order],
        [CLASS_NAMES.index("person"), CLASS_NAMES.index("car"), CLASS_NAMES.index("bus")],
    )
    np.testing.assert_allclose(detections.xyxy[order[0]], _xyxy(40, 30, 20, 40, 0.4), atol=1e-3)
    np.testing.assert_allclose(detections.xyxy[order[1]], _xyxy(90, 50, 30, 20, 0.4), atol=1e-3)


def test_yolov5_layout_multiplies_objectness(tmp_path: Path):
    boxes = [
        (64, 48, 32, 64, 0.9, PERSON, 0.9),  # score 0.81
        (20, 20, 8, 8, 0.3, CAR, 0.9),  # score 0.27
        (100, 60, 8, 8, 0.2, PERSON, 1.0),  # objectness below the threshold
    ]
    model = constant_model(tmp_path / "v5.onnx", v5_table(boxes))
    detector = OnnxDetector(model)
    assert detector.layout == "yolov5"
    detections = detector.detect(_image(256, 192))  # scale 0.5, no padding
    order = np.argsort(-detections.confidence)
    np.testing.assert_allclose(detections.confidence[order], [0.81, 0.27], atol=1e-6)
    np.testing.assert_allclose(detections.xyxy[order[0]], _xyxy(64, 48, 32, 64, 0.5), atol=1e-3)
    # A higher threshold keeps the first only.
    assert len(OnnxDetector(model, confidence=0.5).detect(_image(256, 192))) == 1


def test_yolox_layout_decodes_grid_offsets(tmp_path: Path):
    width, height = 128, 96
    table = np.zeros((1, grid_cells(width, height), 85), np.float32)
    # Stride 8, cell (column 5, row 3): row 3 * 16 + 5.
    table[0, 3 * 16 + 5, :5] = (0.5, 0.25, math.log(3.0), math.log(5.0), 0.9)
    table[0, 3 * 16 + 5, 5 + PERSON] = 1.0
    # Stride 16, cell (column 2, row 1): after the 12 x 16 stride-8 cells.
    table[0, 192 + 1 * 8 + 2, :5] = (0.0, 0.5, math.log(2.0), math.log(1.0), 0.8)
    table[0, 192 + 1 * 8 + 2, 5 + CAR] = 1.0
    detector = OnnxDetector(constant_model(tmp_path / "yolox.onnx", table))
    assert detector.layout == "yolox"
    detections = detector.detect(_image(width, height))  # scale 1
    order = np.argsort(-detections.confidence)
    np.testing.assert_allclose(detections.xyxy[order[0]], _xyxy(44, 26, 24, 40, 1.0), atol=1e-3)
    np.testing.assert_allclose(detections.xyxy[order[1]], _xyxy(32, 24, 32, 16, 1.0), atol=1e-3)
    assert detections.class_id[order].tolist() == [0, CLASS_NAMES.index("car")]


def test_a_yolox_export_with_decoding_inside_reads_pixels(tmp_path: Path):
    width, height = 128, 96
    table = np.zeros((1, grid_cells(width, height), 85), np.float32)
    table[0, :, 2:4] = 40.0  # every row's size in pixels: not log sizes
    table[0, 0, :5] = (64, 48, 32, 64, 0.9)
    table[0, 0, 5 + PERSON] = 1.0
    detector = OnnxDetector(constant_model(tmp_path / "decoded.onnx", table))
    assert detector.layout == "yolov5"
    detections = detector.detect(_image(width, height))
    np.testing.assert_allclose(detections.xyxy[0], _xyxy(64, 48, 32, 64, 1.0), atol=1e-3)


def test_ultralytics_names_metadata_maps_classes(tmp_path: Path):
    boxes = [(40, 30, 20, 40, 0, 0.9), (90, 50, 30, 20, 1, 0.8)]
    model = constant_model(
        tmp_path / "two.onnx", v8_table(boxes, classes=2), names={0: "car", 1: "pedestrian"}
    )
    detector = OnnxDetector(model)
    assert detector.class_names == ("car", "pedestrian")
    detections = detector.detect(_image(128, 96))
    order = np.argsort(-detections.confidence)
    assert detections.class_id[order].tolist() == [
        CLASS_NAMES.index("car"), CLASS_NAMES.index("person")
    ]


def test_dynamic_input_size_and_float16_input(tmp_path: Path):
    from onnx import TensorProto

    table = v8_table([(320, 320, 64, 128, PERSON, 0.9)], width=640, height=640)
    model = constant_model(
        tmp_path / "dynamic.onnx", table, input_shape=("batch", 3, "height", "width"),
        input_type=TensorProto.FLOAT16,
    )
    detector = OnnxDetector(model)
    assert detector.input_size == (640, 640)
    detections = detector.detect(_image(1280, 1280))
    np.testing.assert_allclose(detections.xyxy[0], _xyxy(320, 320, 64, 128, 0.5), atol=1e-2)


def test_nms_is_class_aware_and_best_first():
    xyxy = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], float)
    scores = np.array([0.5, 0.9, 0.8, 0.1])
    classes = np.array([0, 0, 1, 0])
    kept = non_maximum_suppression(xyxy, scores, classes, 0.45)
    assert kept.tolist() == [1, 2, 3]
    assert non_maximum_suppression(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int), 0.5).size == 0


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p / "missing.onnx", "does not exist"),
        (lambda p: _write(p / "model.onnx", b"not a model at all"), "is not an ONNX model"),
        (lambda p: _write(p / "frame.jpg", (Path(__file__).parent / "onnx_models.py")
                          .read_bytes()), "is not an ONNX model"),
        (lambda p: constant_model(p / "classifier.onnx", np.zeros((1, 1000), np.float32)),
         r"output shape \(1, 1000\); expected a YOLO detection output"),
        (lambda p: constant_model(p / "five.onnx", np.zeros((1, 900, 10), np.float32)),
         "5 classes and no class names"),
        (lambda p: constant_model(p / "nms.onnx", np.zeros((1, 300, 6), np.float32),
                                  names={i: f"c{i}" for i in range(80)}),
         "names 80 classes in its metadata but its output has 1"),
        (lambda p: constant_model(p / "grey.onnx", v8_table([]), input_shape=(1, 1, 96, 128)),
         r"expected one image input shaped \(1, 3, height, width\)"),
    ],
)
def test_unusable_models_are_one_clear_sentence(tmp_path: Path, make, message):
    with pytest.raises(ModelError, match=message) as error:
        OnnxDetector(make(tmp_path))
    assert "\n" not in str(error.value)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_detect_refuses_a_non_image(tmp_path: Path):
    from cblrs.errors import CblrsError

    detector = OnnxDetector(constant_model(tmp_path / "v8.onnx", v8_table([])))
    with pytest.raises(CblrsError, match=r"expected an \(H, W, 3\) BGR image"):
        detector.detect(np.zeros((10, 10), np.uint8))


# ---------------------------------------------------------------- the shipped YOLOX-Nano


def test_shipped_yolox_nano_finds_the_people_of_real_frames(yolox_model, multiviewx_real_root):
    scene = load_scene(multiviewx_real_root).select_frames(1, 2)
    paths = scene_image_paths(multiviewx_real_root, len(scene.cameras), scene.frames)
    detector = OnnxDetector(yolox_model)
    assert detector.layout == "yolox" and detector.input_size == (416, 416)
    matched = total = 0
    for position, row in enumerate(paths):
        for camera, path in enumerate(row):
            detections = detector.detect(read_image(path))
            assert set(detections.class_id.tolist()) <= {0, 1, 2, 3, 4, 5}
            truth = scene.detections[position][camera]
            if len(truth) and len(detections):
                matched += int((box_iou(truth.xyxy, detections.xyxy).max(axis=1) >= 0.5).sum())
            total += len(truth)
    # The whole frame letterboxed to 416 px finds the near half of the annotated people.
    assert 0.25 < matched / total < 0.7
    assert COCO_COUNT == len(COCO_CLASS_NAMES)
