"""ONNX object detectors on the CPU (onnxruntime): YOLOX and Ultralytics YOLOv5/v8/v11 exports.

Users bring their own model file; nothing is downloaded. Three output layouts are read,
detected from the output's shape (or named with ``layout=``):

==========  ======================  =================================================
layout      output shape            rows
==========  ======================  =================================================
``yolox``   (1, N, 5 + C)           YOLOX's own export: for each of the N grid cells of
                                    strides 8, 16, 32 raw offsets cx, cy, log w, log h
                                    (decoded as ``(xy + cell) * stride``,
                                    ``exp(wh) * stride``), objectness, C class scores
``yolov5``  (1, N, 5 + C)           Ultralytics YOLOv5 (and YOLOv7, or a YOLOX export
                                    with decoding inside): cx, cy, w, h in input
                                    pixels, objectness, C class scores; N = 3 anchors
                                    per cell
``yolov8``  (1, 4 + C, N)           Ultralytics YOLOv8 / v11: cx, cy, w, h in input
                                    pixels, C class scores, no objectness
==========  ======================  =================================================

A (1, N, 5 + C) output with exactly one row per grid cell is YOLOX, unless its box sizes
are plainly pixels (a YOLOX export with decoding inside), which then reads as ``yolov5``.

Pre-processing follows the family: YOLOX takes BGR 0..255, Ultralytics RGB 0..1; both
get the image letterboxed (the long side scaled to the input, padded with grey 114 at the
bottom and right). Scores are objectness x class score (YOLOX, v5) or the class score
(v8); classes map to cblrs's (person, car, bicycle, motorcycle, bus, truck) by name: the
model's ``names`` metadata (Ultralytics writes it) or, for 80 classes without names, COCO's
order. Other classes are dropped; class-aware NMS follows.
"""

from __future__ import annotations

import ast
import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import Detections
from cblrs.detectors.base import COCO_CLASS_NAMES, class_map, non_maximum_suppression
from cblrs.errors import CblrsError

logger = logging.getLogger(__name__)

LAYOUTS = ("auto", "yolox", "yolov5", "yolov8")
DEFAULT_CONFIDENCE = 0.25
"""Minimum score (Ultralytics' prediction default)."""
DEFAULT_IOU = 0.45
"""NMS IoU threshold (YOLOX's default)."""
DEFAULT_DYNAMIC_SIZE = 640
"""Input side for models exported with a dynamic input size (Ultralytics' default)."""
PAD_VALUE = 114
_STRIDES = (8, 16, 32)
# A raw YOLOX row holds log(w / stride): a median above this would mean boxes of
# e^8 x 8 = 24 000 pixels, so such values are already pixels.
_RAW_LOG_SIZE_LIMIT = 8.0


class ModelError(CblrsError):
    """A model file that cannot be used as a detector."""


def letterbox(
    image: NDArray[np.uint8], size: tuple[int, int]
) -> tuple[NDArray[np.uint8], float]:
    """The image scaled to fit ``size`` = (width, height), padded with grey at bottom/right.

    Returns:
        ``(canvas, scale)``: (height, width, 3) uint8 and model pixels per image pixel.
    """
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    width, height = size
    scale = min(width / image.shape[1], height / image.shape[0])
    resized_width = max(1, min(width, round(image.shape[1] * scale)))
    resized_height = max(1, min(height, round(image.shape[0] * scale)))
    canvas = np.full((height, width, 3), PAD_VALUE, dtype=np.uint8)
    if (resized_width, resized_height) == (image.shape[1], image.shape[0]):
        canvas[: image.shape[0], : image.shape[1]] = image
    else:
        interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        canvas[:resized_height, :resized_width] = cv2.resize(
            image, (resized_width, resized_height), interpolation=interpolation
        )
    return canvas, scale


class OnnxDetector:
    """A YOLO-family detector from an ONNX file, run with onnxruntime on the CPU.

    Args:
        model: path of the ``.onnx`` file.
        confidence: minimum score (objectness x class score, or class score for v8).
        iou: NMS IoU threshold (class-aware).
        layout: ``"auto"`` (from the output shape), ``"yolox"``, ``"yolov5"`` or ``"yolov8"``.
        input_size: (width, height) for a model with a dynamic input size (default 640 x 640);
            ignored when the model fixes it.
        threads: onnxruntime intra-op threads (None: onnxruntime's default, all cores).

    Raises:
        ModelError: the file is missing, is not ONNX, or its input/output is not a YOLO
            detector's (one sentence saying what was found and what was expected).

    Example:
        >>> detector = OnnxDetector("../shared/models/yolox_nano.onnx")  # doctest: +SKIP
        >>> detections = detector.detect(cv2.imread("frame.jpg"))  # doctest: +SKIP
    """

    def __init__(
        self,
        model: str | Path,
        confidence: float = DEFAULT_CONFIDENCE,
        iou: float = DEFAULT_IOU,
        layout: str = "auto",
        input_size: tuple[int, int] | None = None,
        threads: int | None = None,
    ):
        if layout not in LAYOUTS:
            raise ModelError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}.")
        if not 0.0 <= confidence <= 1.0:
            raise ModelError(f"confidence must be within 0..1, got {confidence}.")
        if not 0.0 < iou <= 1.0:
            raise ModelError(f"the NMS IoU threshold must be within (0, 1], got {iou}.")
        self.path = Path(model)
        self.confidence = float(confidence)
        self.iou = float(iou)
        self._session = _open_session(self.path, threads)
        self._input_name, self.input_size, self._input_dtype = _read_input(
            self._session, self.path, input_size
        )
        # One run on a grey canvas reads the output layout (and warms the session up).
        self._ultralytics_input = False
        output = self._run(
            np.full((self.input_size[1], self.input_size[0], 3), PAD_VALUE, np.uint8)
        )
        self.layout, class_count, decoded = _read_layout(output, self.input_size, layout, self.path)
        self._decoded = decoded
        self.class_names = _class_names(self._session, class_count, self.path)
        self._class_map = class_map(self.class_names)
        self._kept_classes = np.flatnonzero(self._class_map >= 0)
        # YOLOX is trained on BGR 0..255; Ultralytics on RGB 0..1.
        self._ultralytics_input = self.layout != "yolox" and not (
            self.layout == "yolov5" and decoded == "yolox"
        )
        self._grid, self._grid_strides = _yolox_grid(self.input_size)
        logger.debug(
            "%s: layout %s, input %dx%d, %d classes (%d tracked)",
            self.path, self.layout, *self.input_size, class_count, len(self._kept_classes),
        )

    # ------------------------------------------------------------------ public
    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Boxes of one image (the whole image letterboxed to the model's input).

        Args:
            image: (H, W, 3) uint8 BGR image (as ``cv2.imread`` gives).

        Returns:
            The boxes after NMS, in image pixels, cblrs class ids, best first.
        """
        candidates = self.candidates(image)
        kept = non_maximum_suppression(
            candidates.xyxy, candidates.confidence, candidates.class_id, self.iou
        )
        return candidates[kept]

    def candidates(self, image: NDArray[np.uint8]) -> Detections:
        """Every box above the confidence threshold, before NMS (for merging tiles)."""
        _check_image(image)
        canvas, scale = letterbox(image, self.input_size)
        rows = self._run(canvas)[0]
        xyxy, scores, class_id = self._decode(rows)
        xyxy /= scale
        height, width = image.shape[:2]
        np.clip(xyxy[:, 0::2], 0.0, float(width), out=xyxy[:, 0::2])
        np.clip(xyxy[:, 1::2], 0.0, float(height), out=xyxy[:, 1::2])
        usable = (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])
        return Detections(
            xyxy=xyxy[usable], confidence=scores[usable], class_id=class_id[usable]
        )

    def __repr__(self) -> str:
        return (
            f"OnnxDetector({str(self.path)!r}, layout={self.layout!r}, "
            f"input={self.input_size[0]}x{self.input_size[1]}, confidence={self.confidence}, "
            f"iou={self.iou})"
        )

    # ------------------------------------------------------------------ internals
    def _run(self, canvas: NDArray[np.uint8]) -> NDArray[np.float32]:
        if self._ultralytics_input:
            tensor = canvas[:, :, ::-1].astype(np.float32) / 255.0
        else:
            tensor = canvas.astype(np.float32)
        tensor = np.ascontiguousarray(tensor.transpose(2, 0, 1)[None], dtype=self._input_dtype)
        output = self._session.run(None, {self._input_name: tensor})[0]
        return np.asarray(output, dtype=np.float32)

    def _decode(
        self, rows: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """(K, 4) xyxy model pixels, (K,) scores, (K,) cblrs class ids above the threshold."""
        boxes: NDArray[np.float64]
        if self.layout == "yolov8":
            rows = rows.T
            boxes, scores = rows[:, :4].astype(np.float64), rows[:, 4:]
        else:
            # Objectness bounds the score: filter on it before touching the class columns.
            candidates = np.flatnonzero(rows[:, 4] >= self.confidence)
            rows = rows[candidates]
            boxes = rows[:, :4].astype(np.float64)
            scores = rows[:, 5:] * rows[:, 4:5]
            if self.layout == "yolox" and self._decoded != "pixels":
                stride = self._grid_strides[candidates, None]
                with np.errstate(over="ignore"):
                    boxes = np.column_stack(
                        [
                            (boxes[:, :2] + self._grid[candidates]) * stride,
                            np.exp(np.minimum(boxes[:, 2:4], 30.0)) * stride,
                        ]
                    )
        tracked = scores[:, self._kept_classes]
        best = np.argmax(tracked, axis=1) if tracked.shape[1] else np.zeros(len(rows), np.int64)
        score = tracked[np.arange(len(tracked)), best] if tracked.shape[1] else np.zeros(len(rows))
        keep = score >= self.confidence
        boxes = np.asarray(boxes, dtype=np.float64)[keep]
        centre, size = boxes[:, :2], boxes[:, 2:4]
        xyxy = np.column_stack([centre - size / 2, centre + size / 2])
        class_id = self._class_map[self._kept_classes[best[keep]]]
        return xyxy, score[keep].astype(np.float64), class_id.astype(np.int64)


# ---------------------------------------------------------------------------- helpers


def _check_image(image: NDArray[np.uint8]) -> None:
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
        shape = getattr(image, "shape", None)
        raise CblrsError(f"expected an (H, W, 3) BGR image, got shape {shape}.")
    if image.dtype != np.uint8:
        raise CblrsError(f"expected a uint8 image, got {image.dtype}.")


def _open_session(path: Path, threads: int | None):
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist (nothing is downloaded at run time).")
    try:
        # lazy: onnxruntime takes ~80 ms to import; only a detector needs it
        import onnxruntime
    except ImportError:  # pragma: no cover - a core dependency
        raise ImportError("the ONNX detector needs onnxruntime: pip install onnxruntime") from None
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3  # errors only; they become one sentence below
    # Threads that wait for work sleep instead of spinning: spinning burned as much CPU again
    # as the inference (60 YOLOX-Nano runs: 2.1 vs 1.0 CPU-s), taken from whatever shares the
    # machine (the other cameras, the broker), and on a loaded machine it was slower too.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    if threads is not None:
        options.intra_op_num_threads = int(threads)
    try:
        return onnxruntime.InferenceSession(
            str(path), options, providers=["CPUExecutionProvider"]
        )
    except Exception as error:  # onnxruntime raises its own exception types
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ModelError(
            f"{path} is not an ONNX model that onnxruntime can load ({reason[:160]})."
        ) from None


def _read_input(session, path: Path, input_size: tuple[int, int] | None):
    inputs = session.get_inputs()
    expected = "one image input shaped (1, 3, height, width)"
    if len(inputs) != 1:
        raise ModelError(f"{path} has {len(inputs)} inputs; a YOLO detector has {expected}.")
    (tensor,) = inputs
    shape = list(tensor.shape)
    if len(shape) != 4 or shape[1] not in (3, "3"):
        raise ModelError(f"{path} takes input {tensor.name!r} shaped {shape}; expected {expected}.")
    dtypes = {"tensor(float)": np.float32, "tensor(float16)": np.float16}
    if tensor.type not in dtypes:
        raise ModelError(f"{path} takes {tensor.type} input; expected float32 or float16 images.")
    height, width = shape[2], shape[3]
    if isinstance(height, int) and isinstance(width, int) and height > 0 and width > 0:
        size = (width, height)
    else:
        size = input_size or (DEFAULT_DYNAMIC_SIZE, DEFAULT_DYNAMIC_SIZE)
    if min(size) < 32 or size[0] % 32 or size[1] % 32:
        raise ModelError(f"input size {size[0]}x{size[1]} must be a multiple of 32 (strides 8-32).")
    return tensor.name, (int(size[0]), int(size[1])), dtypes[tensor.type]


def _grid_cells(size: tuple[int, int]) -> int:
    width, height = size
    return sum((height // stride) * (width // stride) for stride in _STRIDES)


def _yolox_grid(size: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cell corners (N, 2) and strides (N,) in YOLOX's row order (stride, row, column)."""
    width, height = size
    cells, strides = [], []
    for stride in _STRIDES:
        columns, rows = np.meshgrid(np.arange(width // stride), np.arange(height // stride))
        cells.append(np.column_stack([columns.ravel(), rows.ravel()]))
        strides.append(np.full(columns.size, float(stride)))
    return np.concatenate(cells).astype(np.float64), np.concatenate(strides)


def _read_layout(
    output: NDArray[np.float32], size: tuple[int, int], layout: str, path: Path
) -> tuple[str, int, str]:
    """``(layout, class count, box form)`` of a model's first output.

    The box form is ``"raw"`` (YOLOX grid offsets), ``"pixels"`` or ``"yolox"`` (a YOLOX
    export that decodes inside the model: pixels, but YOLOX's BGR 0..255 input).
    """
    expected = (
        "a YOLO detection output: (1, N, 5 + classes) for YOLOX / YOLOv5 or "
        "(1, 4 + classes, N) for YOLOv8 / v11"
    )
    if output.ndim != 3 or output.shape[0] != 1:
        raise ModelError(f"{path} has output shape {tuple(output.shape)}; expected {expected}.")
    _, first, second = output.shape
    if layout == "auto":
        layout = "yolov8" if first < second else "yolox" if first == _grid_cells(size) else "yolov5"
    if layout == "yolov8":
        count, classes = second, first - 4
    else:
        count, classes = first, second - 5
    if classes < 1 or count < 1:
        raise ModelError(
            f"{path} has output shape {tuple(output.shape)}, which leaves no class scores for "
            f"layout {layout}; expected {expected}."
        )
    if layout == "yolox" and count != _grid_cells(size):
        raise ModelError(
            f"{path}: a YOLOX output at {size[0]}x{size[1]} has {_grid_cells(size)} rows "
            f"(strides 8, 16, 32), this one has {count}."
        )
    form = "pixels"
    if layout == "yolox":
        if float(np.median(output[0, :, 2:4])) > _RAW_LOG_SIZE_LIMIT:
            # Boxes already in pixels: read it as the v5 layout, keep YOLOX's input.
            logger.info("%s: a YOLOX export with decoding inside; boxes are read as pixels", path)
            return "yolov5", classes, "yolox"
        form = "raw"
    return layout, classes, form


def _class_names(session, count: int, path: Path) -> tuple[str, ...]:
    metadata = session.get_modelmeta().custom_metadata_map or {}
    text = metadata.get("names")
    if text:
        try:
            names = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            names = None
        if isinstance(names, dict):
            try:
                names = [names[key] for key in sorted(names, key=int)]
            except (TypeError, ValueError):
                names = None
        if isinstance(names, list | tuple) and all(isinstance(name, str) for name in names):
            if len(names) != count:
                raise ModelError(
                    f"{path} names {len(names)} classes in its metadata but its output has "
                    f"{count} class scores (an export with NMS inside, or another layout?)."
                )
            return tuple(names)
        logger.warning("%s: unreadable 'names' metadata; assuming COCO's classes", path)
    if count != len(COCO_CLASS_NAMES):
        raise ModelError(
            f"{path} has {count} classes and no class names in its metadata; without names "
            f"cblrs reads only COCO's {len(COCO_CLASS_NAMES)} classes."
        )
    return COCO_CLASS_NAMES
