"""Where an edge camera's detections come from.

A source yields :class:`SourceFrame` objects — frame number, capture time relative to the
start of the recording (seconds, ``None`` for a live feed) and the frame's boxes — in capture
order. Sources:

* :func:`mot_source` — a MOT-format detections file (``frame,id,x,y,w,h,conf,...``);
* :func:`aicity_source` — an AI City format file (``camera obj frame x y w h ...``);
* :func:`scene_source` — one camera of a WILDTRACK / MultiviewX folder (its annotations as
  detections);
* :func:`video_source` / :func:`image_folder_source` — frames run through a
  :class:`Detector`: :class:`YoloDetector` (Ultralytics, optional extra ``cblrs[yolo]``, local
  weights only) or the dependency-free :class:`ColourBlobDetector`.

Images never leave this module: only the detector's boxes go on.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CLASS_NAMES, Detections
from cblrs.errors import CblrsError, DatasetError

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


@dataclass(frozen=True, eq=False)
class SourceFrame:
    """One captured frame's detections.

    Attributes:
        frame: frame number in the source's own numbering.
        timestamp: capture time in seconds since the start of the recording, or ``None`` when
            the frame is live (the camera node then stamps it with the wall clock).
        detections: the frame's boxes.
    """

    frame: int
    timestamp: float | None
    detections: Detections


@runtime_checkable
class Detector(Protocol):
    """Anything that turns an image into boxes."""

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Detect objects.

        Args:
            image: (H, W, 3) uint8 image in OpenCV's BGR channel order.

        Returns:
            The boxes in pixels, with class ids from :data:`cblrs.detections.CLASS_NAMES`.
        """
        ...


# -- detection files ---------------------------------------------------------------------


def _read_table(path: Path, what: str) -> list[list[str]]:
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise DatasetError(f"{what} file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"cannot read {what} file {path}: {error}.") from None
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        rows.append(line.replace(",", " ").split())
    return rows


def _numbers(rows: list[list[str]], columns: int, path: Path, what: str) -> NDArray[np.float64]:
    table = np.zeros((len(rows), columns))
    for number, row in enumerate(rows, start=1):
        if len(row) < columns:
            raise DatasetError(
                f"{path}: data line {number} has {len(row)} fields; a {what} line needs at "
                f"least {columns}."
            )
        try:
            table[number - 1] = [float(value) for value in row[:columns]]
        except ValueError:
            raise DatasetError(f"{path}: data line {number} is not numeric: {row}.") from None
    if not np.all(np.isfinite(table)):
        raise DatasetError(f"{path}: contains NaN or infinite values.")
    return table


def frames_from_table(
    frame: NDArray[np.int64],
    xyxy: NDArray[np.float64],
    confidence: NDArray[np.float64],
    object_id: NDArray[np.int64],
    fps: float,
    class_id: int = 0,
    frame_step: int | None = None,
) -> Iterator[SourceFrame]:
    """Group detection rows by frame, filling frames without detections with empty frames.

    Args:
        frame: (N,) int64 frame number of each row.
        xyxy: (N, 4) float64 boxes, pixels.
        confidence: (N,) float64 scores.
        object_id: (N,) int64 identities (-1 if unknown).
        fps: frames per second of the frame numbering; ``timestamp = frame / fps``.
        class_id: class of every row.
        frame_step: emit every ``frame_step``-th frame between the first and the last one
            (default: the greatest common divisor of the gaps, so a file annotated every 5th
            frame yields every 5th frame, including those where nothing was detected).
    """
    if fps <= 0:
        raise CblrsError(f"fps must be positive, got {fps}.")
    if len(frame) == 0:
        return
    present = np.unique(frame)
    if frame_step is None:
        gaps = np.diff(present)
        frame_step = int(np.gcd.reduce(gaps)) if len(gaps) else 1
    if frame_step < 1:
        raise CblrsError(f"frame step must be at least 1, got {frame_step}.")
    order = np.argsort(frame, kind="stable")
    frame, xyxy, confidence, object_id = (
        frame[order], xyxy[order], confidence[order], object_id[order]
    )
    starts = np.searchsorted(frame, present)
    ends = np.searchsorted(frame, present, side="right")
    rows_of = {int(f): (s, e) for f, s, e in zip(present, starts, ends, strict=True)}
    for number in range(int(present[0]), int(present[-1]) + 1, frame_step):
        start, end = rows_of.get(number, (0, 0))
        detections = Detections(
            xyxy=xyxy[start:end],
            confidence=confidence[start:end],
            class_id=np.full(end - start, class_id, np.int64),
            object_id=object_id[start:end],
        )
        yield SourceFrame(number, number / fps, detections)


def mot_source(
    path: str | Path, fps: float, class_id: int = 0, frame_step: int | None = None
) -> Iterator[SourceFrame]:
    """Detections from a MOT Challenge file: ``frame,id,x,y,w,h,conf[,...]`` (pixels).

    A negative confidence (ground-truth files use -1 or flags) is read as 1.

    Raises:
        DatasetError: the file is missing or a line is malformed.
    """
    path = Path(path)
    rows = _read_table(path, "MOT detections")
    table = _numbers(rows, 6, path, "MOT (frame,id,x,y,w,h[,conf])")
    confidence = np.array(
        [float(row[6]) if len(row) > 6 else 1.0 for row in rows], dtype=np.float64
    )
    confidence[~(confidence >= 0)] = 1.0
    confidence = np.minimum(confidence, 1.0)
    xyxy = np.column_stack(
        [table[:, 2], table[:, 3], table[:, 2] + table[:, 4], table[:, 3] + table[:, 5]]
    )
    yield from frames_from_table(
        table[:, 0].astype(np.int64), xyxy, confidence, table[:, 1].astype(np.int64),
        fps, class_id, frame_step,
    )


def aicity_source(
    path: str | Path,
    fps: float,
    camera_number: int | None = None,
    class_id: int = 0,
    frame_step: int | None = None,
) -> Iterator[SourceFrame]:
    """Detections from an AI City file: ``camera obj frame x y w h [x_world y_world]``.

    Args:
        path: the text file (space or comma separated).
        fps: frames per second of the frame numbering.
        camera_number: keep only rows of this camera column value (default: all rows).
        class_id: class of every row.
        frame_step: see :func:`frames_from_table`.
    """
    path = Path(path)
    rows = _read_table(path, "AI City detections")
    table = _numbers(rows, 7, path, "AI City (camera obj frame x y w h)")
    if camera_number is not None:
        keep = table[:, 0] == camera_number
        if not keep.any() and len(table):
            cameras = sorted({int(value) for value in table[:, 0]})
            raise DatasetError(f"{path} has no rows of camera {camera_number}; it has {cameras}.")
        table = table[keep]
    xyxy = np.column_stack(
        [table[:, 3], table[:, 4], table[:, 3] + table[:, 5], table[:, 4] + table[:, 6]]
    )
    yield from frames_from_table(
        table[:, 2].astype(np.int64), xyxy, np.ones(len(table)), table[:, 1].astype(np.int64),
        fps, class_id, frame_step,
    )


def scene_source(scene: Any, camera: str | int) -> Iterator[SourceFrame]:
    """One camera of a loaded :class:`~cblrs.datasets.scene.Scene`, frame by frame.

    Args:
        scene: the scene (e.g. from :func:`cblrs.datasets.load_scene`).
        camera: the camera's name or index.

    Raises:
        DatasetError: no such camera.
    """
    index = camera_position(scene.camera_names, camera)
    for position, frame in enumerate(scene.frames):
        yield SourceFrame(
            int(frame), float(scene.timestamps[position]), scene.detections[position][index]
        )


def camera_position(names: list[str], camera: str | int) -> int:
    if isinstance(camera, int) or (isinstance(camera, str) and camera.isdigit()):
        index = int(camera)
        if 0 <= index < len(names):
            return index
    elif camera in names:
        return names.index(camera)
    raise DatasetError(f"no camera {camera!r} in the dataset; cameras: {', '.join(names)}.")


# -- images through a detector -----------------------------------------------------------


def video_source(
    path: str | Path, detector: Detector, fps: float | None = None, live: bool = False
) -> Iterator[SourceFrame]:
    """Frames of a video file (or a camera device / stream URL with ``live=True``).

    Args:
        path: the video file, or a stream URL / device for a live camera.
        detector: turns each frame into boxes.
        fps: override the file's frame rate (timestamps are ``frame / fps``).
        live: frames carry no recorded timestamp; the camera node stamps them on capture.

    Raises:
        DatasetError: the video cannot be opened.
    """
    import cv2

    target: Any = int(path) if isinstance(path, str) and path.isdigit() else str(path)
    if not live and not Path(str(path)).is_file():
        raise DatasetError(f"video file {path} does not exist.")
    capture = cv2.VideoCapture(target)
    if not capture.isOpened():
        raise DatasetError(f"cannot open video {path}.")
    rate = fps or capture.get(cv2.CAP_PROP_FPS) or 0.0
    if not live and not (rate > 0 and math.isfinite(rate)):
        capture.release()
        raise DatasetError(f"{path} has no frame rate; give it with --fps.")
    try:
        number = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            detections = detector.detect(np.asarray(image, np.uint8))
            yield SourceFrame(number, None if live else number / rate, detections)
            number += 1
    finally:
        capture.release()


def image_folder_source(
    folder: str | Path, detector: Detector, fps: float
) -> Iterator[SourceFrame]:
    """Image files of a folder in name order, as frames ``0, 1, ...`` at ``fps``.

    Raises:
        DatasetError: the folder is missing, empty or an image cannot be read.
    """
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"image folder {folder} does not exist.")
    if fps <= 0:
        raise CblrsError(f"fps must be positive, got {fps}.")
    paths = sorted(path for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise DatasetError(f"{folder} holds no images ({', '.join(IMAGE_SUFFIXES)}).")
    for number, path in enumerate(paths):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f"cannot read image {path}.")
        yield SourceFrame(number, number / fps, detector.detect(np.asarray(image, np.uint8)))


class ColourBlobDetector:
    """Boxes around connected regions of one colour — a detector with no model.

    Useful for tests, demos and marker-based setups (e.g. coloured hats seen from above).

    Args:
        colour_rgb: the colour to find, (R, G, B) 0..255.
        tolerance: maximum absolute difference per channel.
        min_area: smallest region in pixels.
        class_id: class given to every box.
    """

    def __init__(
        self,
        colour_rgb: tuple[int, int, int],
        tolerance: int = 30,
        min_area: int = 20,
        class_id: int = 0,
    ):
        if len(colour_rgb) != 3 or not all(0 <= int(value) <= 255 for value in colour_rgb):
            raise CblrsError(f"blob colour must be three values 0..255, got {colour_rgb}.")
        self.colour_bgr = np.array(colour_rgb[::-1], dtype=np.int16)
        self.tolerance = int(tolerance)
        self.min_area = int(min_area)
        self.class_id = int(class_id)

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Boxes ``(x, y, x + w, y + h)`` of each region of at least ``min_area`` pixels."""
        import cv2

        if image.ndim != 3 or image.shape[2] != 3:
            raise CblrsError(f"expected an (H, W, 3) image, got shape {image.shape}.")
        difference = np.abs(image.astype(np.int16) - self.colour_bgr).max(axis=2)
        mask = (difference <= self.tolerance).astype(np.uint8)
        count, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        stats = stats[1:count]
        stats = stats[stats[:, cv2.CC_STAT_AREA] >= self.min_area]
        x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
        width, height = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
        xyxy = np.column_stack([x, y, x + width, y + height]).astype(np.float64).reshape(-1, 4)
        order = np.lexsort((xyxy[:, 1], xyxy[:, 0]))
        return Detections(
            xyxy=xyxy[order],
            confidence=np.ones(len(xyxy)),
            class_id=np.full(len(xyxy), self.class_id, np.int64),
        )


class YoloDetector:
    """Ultralytics YOLO with local weights (``pip install cblrs[yolo]``).

    Nothing is downloaded: ``weights`` must be an existing file (a ``.pt`` or exported model).
    Classes not in :data:`cblrs.detections.CLASS_NAMES` are dropped.

    Args:
        weights: path of the model file.
        confidence: minimum score.
        device: ``"cpu"``, ``"0"``, ... passed to Ultralytics.

    Raises:
        ImportError: ultralytics is not installed.
        CblrsError: the weights file does not exist.
    """

    def __init__(self, weights: str | Path, confidence: float = 0.25, device: str = "cpu"):
        weights = Path(weights)
        if not weights.is_file():
            raise CblrsError(
                f"YOLO weights {weights} do not exist; give a local model file with --weights "
                "(nothing is downloaded at run time)."
            )
        try:
            from ultralytics import YOLO
        except ImportError:
            raise ImportError(
                "the YOLO detector needs ultralytics: pip install cblrs[yolo]"
            ) from None
        self._model = YOLO(str(weights))
        self.confidence = float(confidence)
        self.device = device

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        results = self._model.predict(
            image, conf=self.confidence, device=self.device, verbose=False
        )
        return detections_from_ultralytics(results[0])


def detections_from_ultralytics(result: Any) -> Detections:
    """Map one ``ultralytics.engine.results.Results`` to :class:`Detections`.

    Uses ``result.names`` (class index -> name) and ``result.boxes.xyxy`` / ``.conf`` /
    ``.cls`` (torch tensors or arrays). Boxes whose class name is not in
    :data:`CLASS_NAMES` (the COCO names person, car, bicycle, motorcycle, bus, truck) are
    dropped.
    """
    boxes = result.boxes
    if boxes is None:
        return Detections.empty()
    xyxy = _to_numpy(boxes.xyxy).astype(np.float64).reshape(-1, 4)
    confidence = _to_numpy(boxes.conf).astype(np.float64).reshape(-1)
    model_class = _to_numpy(boxes.cls).astype(np.int64).reshape(-1)
    names = result.names
    class_id = np.array(
        [
            CLASS_NAMES.index(names[value]) if names.get(value) in CLASS_NAMES else -1
            for value in model_class.tolist()
        ],
        dtype=np.int64,
    )
    keep = class_id >= 0
    return Detections(xyxy=xyxy[keep], confidence=confidence[keep], class_id=class_id[keep])


def _to_numpy(value: Any) -> NDArray:
    if hasattr(value, "detach"):
        value = value.detach()
    if hasattr(value, "cpu"):
        value = value.cpu()
    if hasattr(value, "numpy"):
        value = value.numpy()
    return np.asarray(value)
