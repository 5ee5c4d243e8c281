"""A folder of per-camera detection files (MOT format) as a scene's detections.

The most common research workflow: "I ran my detector on the data set's images; give me
global tracks". The folder holds one MOT Challenge file per camera::

    DETECTIONS/Camera1.txt      (or C1.txt: the camera's image folder name)
    DETECTIONS/Camera2.txt
    ...

with lines ``frame,id,x,y,w,h,conf[,...]`` (pixels; ``id`` is ignored, -1 is fine; a
negative confidence reads as 1). A file is named after the camera: its calibration name
(``Camera1``, ``CVLab1``) or its image folder (``C1``), with ``.txt`` or ``.csv``. Frame
numbers are the data set's own: the number of the annotation file
(``annotations_positions/<frame>.json``). In WILDTRACK that is the image number; in the
MultiviewX release in ``../shared`` image ``NNNN.jpg`` is frame ``NNNN+1``.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from cblrs.datasets.detection_tables import mot_source
from cblrs.datasets.images import (
    IMAGE_FOLDER,
    annotated_frames,
    image_frame_offset,
    numbered_images,
)
from cblrs.datasets.scene import Scene
from cblrs.detections import Detections
from cblrs.errors import DatasetError

logger = logging.getLogger(__name__)

SUFFIXES = (".txt", ".csv")


def camera_file_names(scene: Scene) -> dict[str, int]:
    """Accepted file stems -> camera index: calibration names and ``C1..CN``."""
    names = {camera.name: index for index, camera in enumerate(scene.cameras)}
    for index in range(len(scene.cameras)):
        names.setdefault(f"C{index + 1}", index)
    return names


def read_detection_folder(
    scene: Scene,
    folder: str | Path,
    dataset_root: str | Path | None = None,
    class_id: int = 0,
) -> Scene:
    """The scene with the boxes of a folder of per-camera MOT files as its detections.

    Args:
        scene: the data set's scene (its cameras and frame numbers).
        folder: the folder of ``<camera>.txt`` files (see the module notes).
        dataset_root: the data set folder, to recognise frame numbers that are image numbers
            of a release whose images are numbered one less than its frames.
        class_id: the class of every box (MOT files carry none).

    Returns:
        The scene with ``detections`` replaced (``object_id`` from the files' id column).
        Cameras without a file have no detections (a warning names them).

    Raises:
        DatasetError: the folder is missing or empty, a file names no camera of the data
            set, a file is malformed, or its frames are none of the data set's.
    """

    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"detections folder {folder} does not exist.")
    files = sorted(path for path in folder.iterdir() if path.suffix.lower() in SUFFIXES)
    if not files:
        raise DatasetError(
            f"{folder} holds no detection files; expected one MOT file per camera named "
            f"<camera>.txt ({', '.join(scene.camera_names)})."
        )
    accepted = camera_file_names(scene)
    by_camera: dict[int, Path] = {}
    for path in files:
        index = accepted.get(path.stem)
        if index is None:
            raise DatasetError(
                f"detections file {path.name} names no camera of the data set (cameras: "
                f"{', '.join(scene.camera_names)}, or C1..C{len(scene.cameras)})."
            )
        if index in by_camera:
            raise DatasetError(
                f"{by_camera[index].name} and {path.name} both hold camera "
                f"{scene.camera_names[index]}'s detections."
            )
        by_camera[index] = path
    missing = [scene.camera_names[i] for i in range(len(scene.cameras)) if i not in by_camera]
    if missing:
        logger.warning("no detections file for camera(s) %s: they see nothing", ", ".join(missing))

    wanted = {int(frame): position for position, frame in enumerate(scene.frames)}
    detections = [[Detections.empty() for _ in scene.cameras] for _ in scene.frames]
    for index, path in by_camera.items():
        frames = list(mot_source(path, fps=1.0, class_id=class_id, frame_step=1))
        present = {item.frame for item in frames if len(item.detections)}
        if not present:
            logger.warning("%s holds no detections", path)
            continue
        _check_numbering(path, present, scene, dataset_root, index)
        outside = 0
        for item in frames:
            position = wanted.get(item.frame)
            if position is None:
                outside += len(item.detections)
                continue
            detections[position][index] = item.detections
        if outside:
            logger.warning(
                "%s: %d boxes at frames the data set does not have were ignored", path, outside
            )
    return replace(scene, detections=detections)


def _check_numbering(
    path: Path, present: set[int], scene: Scene, dataset_root: str | Path | None, index: int
) -> None:
    """Refuse files numbered by image where images are numbered one less than frames."""
    frames = {int(frame) for frame in scene.frames}
    if present & frames:
        if dataset_root is not None and not present <= frames:
            images = Path(dataset_root) / IMAGE_FOLDER / f"C{index + 1}"
            if images.is_dir():
                numbers = set(numbered_images(images))
                everything = annotated_frames(dataset_root)
                shifted = bool(numbers) and image_frame_offset(numbers, everything) == 1
                if shifted and present <= numbers:
                    raise DatasetError(
                        f"{path.name} is numbered like the image files (frames "
                        f"{min(present)}..{max(present)}), but this data set's image NNNN is "
                        "frame NNNN+1; add 1 to its frame numbers."
                    )
        return
    raise DatasetError(
        f"{path.name} has detections at frames {min(present)}..{max(present)}, none of the "
        f"data set's frames {int(np.min(scene.frames))}..{int(np.max(scene.frames))} (frame "
        "numbers must be those of the annotation files)."
    )
