"""Where an edge camera's detections come from.

A source yields :class:`SourceFrame` objects — frame number, capture time relative to the
start of the recording (seconds, ``None`` for a live feed) and the frame's boxes — in capture
order. Sources:

* :func:`mot_source` — a MOT-format detections file (``frame,id,x,y,w,h,conf,...``);
* :func:`aicity_source` — an AI City format file (``camera obj frame x y w h ...``) (both read
  by :mod:`cblrs.datasets.detection_tables`, importable from here);
* :func:`scene_source` — one camera of a WILDTRACK / MultiviewX folder (its annotations as
  detections);
* :func:`video_source` / :func:`image_folder_source` — frames run through a
  :class:`~cblrs.detectors.Detector` from :mod:`cblrs.detectors` (an ONNX model, Ultralytics,
  or the dependency-free colour blob detector).

Images never leave this module: only the detector's boxes go on.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.datasets.clocks import camera_clocks
from cblrs.datasets.detection_tables import SourceFrame as SourceFrame
from cblrs.datasets.detection_tables import aicity_source as aicity_source
from cblrs.datasets.detection_tables import frames_from_table as frames_from_table
from cblrs.datasets.detection_tables import mot_source as mot_source
from cblrs.datasets.images import IMAGE_SUFFIXES, UnusableImage, read_image
from cblrs.detections import Detections

# The detectors live in cblrs.detectors; these names stay importable from here.
from cblrs.detectors.base import Detector as Detector
from cblrs.detectors.blob import ColourBlobDetector as ColourBlobDetector
from cblrs.detectors.ultralytics_yolo import YoloDetector as YoloDetector
from cblrs.detectors.ultralytics_yolo import (
    detections_from_ultralytics as detections_from_ultralytics,
)
from cblrs.errors import CblrsError, DatasetError

logger = logging.getLogger(__name__)

def scene_source(scene: Any, camera: str | int, clocks: Any = None) -> Iterator[SourceFrame]:
    """One camera of a loaded :class:`~cblrs.datasets.scene.Scene`, frame by frame.

    Args:
        scene: the scene (e.g. from :func:`cblrs.datasets.load_scene`).
        camera: the camera's name or index.
        clocks: a :class:`~cblrs.datasets.clocks.ClockSimulation`: the camera keeps only its
            own frames (frame rate, lost messages) stamped by its own clock.

    Raises:
        DatasetError: no such camera.
    """
    index = camera_position(scene.camera_names, camera)
    if clocks is not None:

        clock = camera_clocks(scene, clocks)[index]
        for position, recorded in zip(clock.frame_index.tolist(), clock.timestamp.tolist(),
                                      strict=True):
            yield SourceFrame(
                int(scene.frames[position]), recorded, scene.detections[position][index]
            )
        return
    for position, frame in enumerate(scene.frames):
        yield SourceFrame(
            int(frame), float(scene.timestamps[position]), scene.detections[position][index]
        )


def camera_position(names: list[str], camera: str | int) -> int:
    """Index of ``camera`` (a name, or an index as int or digits) in ``names``; a clear
    error otherwise."""
    if isinstance(camera, int) or (isinstance(camera, str) and camera.isdigit()):
        index = int(camera)
        if 0 <= index < len(names):
            return index
    elif camera in names:
        return names.index(camera)
    raise DatasetError(f"no camera {camera!r} in the dataset; cameras: {', '.join(names)}.")


# -- images through a detector -----------------------------------------------------------


def video_source(
    path: str | Path,
    detector: Detector,
    fps: float | None = None,
    live: bool = False,
    first: int | None = None,
    last: int | None = None,
) -> Iterator[SourceFrame]:
    """Frames of a video file (or a camera device / stream URL with ``live=True``).

    Args:
        path: the video file, or a stream URL / device for a live camera.
        detector: turns each frame into boxes.
        fps: override the file's frame rate (timestamps are ``frame / fps``).
        live: frames carry no recorded timestamp; the camera node stamps them on capture.
        first, last: only frames ``first..last`` (inclusive, 0-based; None: from the start
            / to the end).

    Raises:
        DatasetError: the video cannot be opened, has no frame rate, or ends before
            ``last`` (raised when the end is reached; earlier frames were yielded).
    """
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
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
    declared = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    try:
        number = 0
        while last is None or number <= last:
            if first is not None and number < first:
                if not capture.grab():
                    break
                number += 1
                continue
            ok, image = capture.read()
            if not ok:
                break
            detections = detector.detect(np.asarray(image, np.uint8))
            yield SourceFrame(number, None if live else number / rate, detections)
            number += 1
    finally:
        capture.release()
    if last is not None and number <= last:
        raise DatasetError(
            f"video {path} ended after {number} frames, before the requested last frame {last}."
        )
    if last is None and not live and declared > number + 1:
        logger.warning(
            "video %s ended after %d of the %d frames its header declares", path, number, declared
        )


def image_folder_source(
    folder: str | Path,
    detector: Detector,
    fps: float,
    first: int | None = None,
    last: int | None = None,
) -> Iterator[SourceFrame]:
    """Image files of a folder in name order, as frames ``0, 1, ...`` at ``fps``.

    Args:
        first, last: only frames ``first..last`` (inclusive; None: from the start / to the end).

    An image file that is empty, cut short or undecodable gives a frame marked
    ``unusable`` (the camera node skips and counts it) instead of ending the stream.

    Raises:
        DatasetError: the folder is missing or empty, or holds fewer images than ``last``
            asks for.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"image folder {folder} does not exist.")
    if fps <= 0:
        raise CblrsError(f"fps must be positive, got {fps}.")
    paths = sorted(path for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise DatasetError(f"{folder} holds no images ({', '.join(IMAGE_SUFFIXES)}).")
    if last is not None and last >= len(paths):
        raise DatasetError(
            f"{folder} holds {len(paths)} images (frames 0..{len(paths) - 1}), fewer than the "
            f"requested last frame {last} needs."
        )
    for number, path in enumerate(paths):
        if (first is not None and number < first) or (last is not None and number > last):
            continue
        try:
            image = read_image(path)
        except UnusableImage as error:
            yield SourceFrame(number, number / fps, Detections.empty(), unusable=error)
            continue
        yield SourceFrame(number, number / fps, detector.detect(image))
