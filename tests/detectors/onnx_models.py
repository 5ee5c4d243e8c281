"""Small real ONNX models with known outputs, built with ``onnx.helper``.

No YOLOv5 / YOLOv8 export can be downloaded here (nothing downloads at run time, and
Ultralytics' weights live on a hub), so the tests build real ONNX files whose output is a
known tensor in each export's layout: ``output = table + 0 * mean(images)``. onnxruntime
loads and runs them exactly like an export, and the adapter's decoding (layout detection,
grid offsets, objectness, letterbox undo, class mapping, NMS) is checked against boxes
placed in the table by hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

COCO_COUNT = 80


def constant_model(
    path: Path,
    table: np.ndarray,
    input_shape: tuple = (1, 3, 96, 128),
    names: dict[int, str] | None = None,
    input_type: int | None = None,
) -> Path:
    """Write an ONNX model mapping ``images`` to the constant ``table`` (float32)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    input_type = TensorProto.FLOAT if input_type is None else input_type
    images = helper.make_tensor_value_info("images", input_type, list(input_shape))
    output = helper.make_tensor_value_info("output", TensorProto.FLOAT, list(table.shape))
    nodes = [
        helper.make_node("Cast", ["images"], ["as_float"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["as_float"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
        helper.make_node("Add", ["table", "nothing"], ["output"]),
    ]
    graph = helper.make_graph(
        nodes,
        "constant_detector",
        [images],
        [output],
        initializer=[
            numpy_helper.from_array(table.astype(np.float32), "table"),
            numpy_helper.from_array(np.zeros((), np.float32), "zero"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    if names is not None:
        entry = model.metadata_props.add()
        entry.key, entry.value = "names", repr(names)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def grid_cells(width: int, height: int) -> int:
    return sum((height // stride) * (width // stride) for stride in (8, 16, 32))


def v8_table(boxes: list[tuple[float, float, float, float, int, float]], classes: int = 80,
             width: int = 128, height: int = 96) -> np.ndarray:
    """(1, 4 + classes, N): columns cx, cy, w, h (model pixels), class scores."""
    count = grid_cells(width, height)
    table = np.zeros((1, 4 + classes, count), np.float32)
    for index, (cx, cy, w, h, class_index, score) in enumerate(boxes):
        table[0, :4, index] = (cx, cy, w, h)
        table[0, 4 + class_index, index] = score
    return table


def v5_table(boxes: list[tuple[float, float, float, float, float, int, float]],
             width: int = 128, height: int = 96) -> np.ndarray:
    """(1, 3 N, 85): rows cx, cy, w, h (model pixels), objectness, class scores."""
    table = np.zeros((1, 3 * grid_cells(width, height), 5 + COCO_COUNT), np.float32)
    for index, (cx, cy, w, h, objectness, class_index, score) in enumerate(boxes):
        table[0, 10 * index, :5] = (cx, cy, w, h, objectness)
        table[0, 10 * index, 5 + class_index] = score
    return table
