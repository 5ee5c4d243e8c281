"""Readers for the WILDTRACK and MultiviewX dataset layouts.

Both layouts share one structure::

    DATASET/
      calibrations/...                       camera calibration (OpenCV FileStorage XML)
      annotations_positions/<frame>.json     one file per annotated frame

Each annotation file is a JSON list of people::

    {"personID": 12, "positionID": 456826,
     "views": [{"viewNum": 0, "xmin": 1510, "ymin": 139, "xmax": 1561, "ymax": 299}, ...]}

with ``(-1, -1, -1, -1)`` meaning "not annotated in that view". They differ in:

================  ===================================  ==================================
                  WILDTRACK                            MultiviewX
================  ===================================  ==================================
cameras           CVLab1-4, IDIAP1-3 (viewNum 0..6)    Camera1..Camera6 (viewNum k = k+1)
intrinsics        ``intrinsic_zero`` / ``_original``   ``intrinsic`` (5 distortion coeffs)
translation unit  centimetres                          metres
file names        8 digits (00000000.json)             5 digits (00000.json)
frame ids         10 fps video, every 5th annotated    consecutive, 2 fps
positionID grid   480 x 1440 cells of 2.5 cm from      1000 x 640 cells of 2.5 cm from
                  (-3 m, -9 m)                         (0 m, 0 m)
================  ===================================  ==================================

:func:`load_scene` turns either into a :class:`cblrs.datasets.scene.Scene` with the annotated
boxes as detections (``object_id`` = personID) and the positions as ground-truth tracks, all
in metres and seconds. Its ground plane is the annotated area grown by ``GROUND_MARGIN_M`` on
every side, so that foot points of people at the border still decode.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from cblrs.calibration import (
    MULTIVIEWX_GROUND,
    WILDTRACK_GROUND,
    read_multiviewx_cameras,
    read_wildtrack_cameras,
)
from cblrs.datasets.scene import Scene
from cblrs.detections import Detections, Tracks, class_id_of
from cblrs.errors import DatasetError
from cblrs.plane import PlaneSpec

logger = logging.getLogger(__name__)

ANNOTATION_FOLDER = "annotations_positions"
LAYOUTS = ("wildtrack", "multiviewx")
# The scene plane is the annotated area grown by this much on every side, metres: people
# standing at the border of the annotated area have foot points that land just outside it
# (box bottoms are not exactly the feet), and a point off the plane has no location (B = 0).
GROUND_MARGIN_M = 2.0


@dataclass(frozen=True)
class _Layout:
    """What differs between the two layouts."""

    name: str
    frames_per_second: float  # of the native frame numbering (timestamp = frame / fps)
    grid_columns: int  # positionID = row * grid_columns + column
    grid_origin: tuple[float, float]  # metres, world position of cell (0, 0)
    cell_size: float  # metres
    ground: tuple[float, float, float, float]  # x0, y0, width, length in metres


_WILDTRACK = _Layout("wildtrack", 10.0, 480, (-3.0, -9.0), 0.025, WILDTRACK_GROUND)
_MULTIVIEWX = _Layout("multiviewx", 2.0, 1000, (0.0, 0.0), 0.025, MULTIVIEWX_GROUND)


def detect_layout(path: str | Path) -> str:
    """``"wildtrack"`` or ``"multiviewx"``, from the calibration files present in ``path``.

    Raises:
        DatasetError: the folder matches neither layout.
    """
    path = Path(path)
    calibrations = path / "calibrations"
    if (calibrations / "intrinsic_zero").is_dir() or (
        calibrations / "extrinsic" / "extr_CVLab1.xml"
    ).is_file():
        return "wildtrack"
    if list((calibrations / "intrinsic").glob("intr_Camera*.xml")):
        return "multiviewx"
    raise DatasetError(
        f"{path} is neither a WILDTRACK layout (calibrations/intrinsic_zero/) nor a MultiviewX "
        "layout (calibrations/intrinsic/intr_Camera1.xml)."
    )


def position_to_world(position_id: np.ndarray, layout: str) -> np.ndarray:
    """World ground positions of annotation ``positionID`` values.

    Args:
        position_id: (N,) int64 grid cell indices.
        layout: ``"wildtrack"`` or ``"multiviewx"``.

    Returns:
        (N, 2) float64 world x, y in metres.
    """
    spec = _layout_spec(layout)
    position_id = np.asarray(position_id, dtype=np.int64)
    column = position_id % spec.grid_columns
    row = position_id // spec.grid_columns
    return np.stack(
        [
            spec.grid_origin[0] + spec.cell_size * column,
            spec.grid_origin[1] + spec.cell_size * row,
        ],
        axis=1,
    ).astype(np.float64).reshape(-1, 2)


def load_scene(path: str | Path, layout: str | None = None, distorted: bool | None = None) -> Scene:
    """Load a WILDTRACK or MultiviewX folder as a :class:`Scene`.

    Args:
        path: the dataset folder (holding ``calibrations/`` and ``annotations_positions/``).
        layout: ``"wildtrack"`` or ``"multiviewx"`` to force a layout; None detects it from
            the calibration files present.
        distorted: whether the cameras model lens distortion. None picks what the annotation
            boxes refer to: WILDTRACK's boxes are on the undistorted frames, so its
            ``intrinsic_zero`` calibration is used; MultiviewX's boxes are on the frames as
            rendered, so its calibration is used as given (with its distortion
            coefficients). True/False force distortion on/off (WILDTRACK: True reads
            ``intrinsic_original``).

    Returns:
        The scene: cameras in view order (``camera_id`` = viewNum), native frame numbers,
        timestamps in seconds (WILDTRACK: frame / 10, MultiviewX: frame / 2), per frame and
        camera the annotated boxes as :class:`Detections` (class person, confidence 1,
        ``object_id`` = personID; boxes reaching outside the image are kept as they are),
        and the ground truth as :class:`Tracks` (``track_id`` = personID, ``world_xy`` in
        metres, ``camera_id`` -1).

    Raises:
        DatasetError: missing folder, unknown layout, no annotation files or a malformed
            annotation file.
        CalibrationError: a missing or unreadable calibration file.

    Example:
        >>> scene = load_scene("../shared/data/wildtrack")  # doctest: +SKIP
        >>> len(scene.cameras), scene.frames[:3], scene.timestamps[:3]  # doctest: +SKIP
        (7, array([ 0,  5, 10]), array([0. , 0.5, 1. ]))
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"dataset folder {path} does not exist.")
    if layout is None:
        layout = detect_layout(path)
    spec = _layout_spec(layout)

    if spec.name == "wildtrack":
        cameras = read_wildtrack_cameras(path, distorted=bool(distorted))
    else:
        cameras = read_multiviewx_cameras(path, use_distortion=distorted is not False)

    annotation_files = _annotation_files(path)
    person = class_id_of("person")
    frames: list[int] = []
    per_frame_detections: list[list[Detections]] = []
    truth_frame: list[np.ndarray] = []
    truth_id: list[np.ndarray] = []
    truth_position: list[np.ndarray] = []
    for frame, file in annotation_files:
        person_ids, position_ids, boxes = _read_people(file, len(cameras))
        frames.append(frame)
        per_camera = []
        for camera_index in range(len(cameras)):
            rows = boxes[camera_index]
            xyxy = np.array([row[1:] for row in rows], dtype=np.float64).reshape(-1, 4)
            object_id = np.array([row[0] for row in rows], dtype=np.int64)
            per_camera.append(
                Detections(
                    xyxy=xyxy,
                    confidence=np.ones(len(rows)),
                    class_id=np.full(len(rows), person, dtype=np.int64),
                    object_id=object_id,
                )
            )
        per_frame_detections.append(per_camera)
        located = position_ids >= 0
        if not located.all():
            logger.warning("%s: %d people without a position", file, int((~located).sum()))
        truth_frame.append(np.full(int(located.sum()), frame, dtype=np.int64))
        truth_id.append(person_ids[located])
        truth_position.append(position_to_world(position_ids[located], spec.name))

    frame_array = np.array(frames, dtype=np.int64)
    all_truth_frames = np.concatenate(truth_frame)
    ground_truth = Tracks(
        frame=all_truth_frames,
        timestamp=all_truth_frames / spec.frames_per_second,
        track_id=np.concatenate(truth_id),
        world_xy=np.concatenate(truth_position),
        # WILDTRACK and MultiviewX annotate people only.
        class_id=np.full(len(all_truth_frames), class_id_of("person"), np.int64),
    )
    x0, y0, width, length = spec.ground
    margin = GROUND_MARGIN_M
    plane = PlaneSpec(
        1, (x0 - margin, y0 - margin), width + 2 * margin, length + 2 * margin, bits=16,
        name=f"{spec.name} ground",
    )
    logger.debug(
        "loaded %s: %d cameras, %d frames, %d ground-truth rows",
        path, len(cameras), len(frame_array), len(ground_truth),
    )
    return Scene(
        name=path.name or spec.name,
        cameras=cameras,
        frames=frame_array,
        timestamps=frame_array / spec.frames_per_second,
        detections=per_frame_detections,
        ground_truth=ground_truth,
        plane=plane,
    )


def _layout_spec(layout: str) -> _Layout:
    if layout == "wildtrack":
        return _WILDTRACK
    if layout == "multiviewx":
        return _MULTIVIEWX
    raise DatasetError(f"unknown dataset layout {layout!r}; expected one of {', '.join(LAYOUTS)}.")


def _annotation_files(path: Path) -> list[tuple[int, Path]]:
    """(frame number, file) of every annotation file, ordered by frame."""
    folder = path / ANNOTATION_FOLDER
    if not folder.is_dir():
        raise DatasetError(f"{path} has no {ANNOTATION_FOLDER}/ folder.")
    files = []
    for file in folder.glob("*.json"):
        if not file.stem.isdigit():
            logger.debug("ignoring %s: its name is not a frame number", file)
            continue
        files.append((int(file.stem), file))
    if not files:
        raise DatasetError(f"{folder} holds no annotation files (<frame>.json).")
    files.sort()
    frames = [frame for frame, _ in files]
    if len(set(frames)) != len(frames):
        raise DatasetError(f"{folder} has two annotation files for the same frame number.")
    return files


class _View(msgspec.Struct):
    """One view of a person, as the annotation files give it (the fast path's schema)."""

    viewNum: int
    xmin: float
    ymin: float
    xmax: float
    ymax: float


class _Person(msgspec.Struct):
    """One annotated person (the fast path's schema; other keys are ignored)."""

    personID: int
    positionID: int
    views: list[_View] = msgspec.field(default_factory=list)


_PEOPLE = msgspec.json.Decoder(list[_Person])


def _read_people(
    file: Path, camera_count: int
) -> tuple[np.ndarray, np.ndarray, list[list[tuple[int, float, float, float, float]]]]:
    """:func:`_parse_people` of :func:`_read_annotation`, typed by msgspec's decoder when the
    file holds JSON integers and numbers where expected (its own checks and conversions, a
    third of the time of converting every value in Python); any other file (strings for
    numbers, a malformed entry) takes the general path, which converts or reports it."""
    try:
        people = _PEOPLE.decode(file.read_bytes())
    except (OSError, ValueError):
        return _parse_people(_read_annotation(file), file, camera_count)
    return _parse_people(people, file, camera_count, typed=True)


def _read_annotation(file: Path) -> list:
    try:
        # msgspec's decoder reads these files in a third of the json module's time.
        people = msgspec.json.decode(file.read_bytes())
    except (OSError, ValueError) as error:  # msgspec.DecodeError is a ValueError
        raise DatasetError(f"annotation file {file} is not valid JSON ({error}).") from None
    if not isinstance(people, list):
        raise DatasetError(f"annotation file {file} must hold a JSON list of people.")
    return people


def _parse_people(
    people: list, file: Path, camera_count: int, typed: bool = False
) -> tuple[np.ndarray, np.ndarray, list[list[tuple[int, float, float, float, float]]]]:
    """personIDs (P,), positionIDs (P,) and per camera the rows (personID, x0, y0, x1, y1).

    ``people``: the decoded JSON list, or with ``typed`` :class:`_Person` objects (already
    checked and converted).
    """
    person_ids: list[int] = []
    position_ids: list[int] = []
    boxes: list[list[tuple[int, float, float, float, float]]] = [[] for _ in range(camera_count)]
    seen: set[int] = set()
    for index, entry in enumerate(people):
        if typed:
            person_id, position_id = entry.personID, entry.positionID
            parsed_views = [(view.viewNum, view.xmin, view.ymin, view.xmax, view.ymax)
                            for view in entry.views]
        else:
            person_id, position_id, parsed_views = _parse_entry(entry, index, file)
        if person_id in seen:
            # Keep the first entry, as the AI City protocol does for (frame, id) duplicates.
            logger.warning("%s: personID %d appears twice; keeping the first", file, person_id)
            continue
        seen.add(person_id)
        person_ids.append(person_id)
        position_ids.append(position_id)
        for view_number, x_min, y_min, x_max, y_max in parsed_views:
            if x_min == y_min == x_max == y_max == -1:
                continue  # not annotated in this view
            if not 0 <= view_number < camera_count:
                raise DatasetError(
                    f"annotation file {file}: viewNum {view_number} of personID {person_id} "
                    f"is not one of the {camera_count} cameras."
                )
            boxes[view_number].append((person_id, x_min, y_min, x_max, y_max))
    return (
        np.array(person_ids, dtype=np.int64),
        np.array(position_ids, dtype=np.int64),
        boxes,
    )


def _parse_entry(
    entry: dict, index: int, file: Path
) -> tuple[int, int, list[tuple[int, float, float, float, float]]]:
    """personID, positionID and views (viewNum, x0, y0, x1, y1) of one decoded JSON entry."""
    try:
        person_id = int(entry["personID"])
        position_id = int(entry["positionID"])
        views = entry.get("views", [])
        parsed_views = [
            (
                int(view["viewNum"]),
                float(view["xmin"]),
                float(view["ymin"]),
                float(view["xmax"]),
                float(view["ymax"]),
            )
            for view in views
        ]
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise DatasetError(
            f"annotation file {file}: entry {index} is malformed ({type(error).__name__}: "
            f"{error}); expected personID, positionID and views with viewNum and "
            "xmin/ymin/xmax/ymax."
        ) from None
    return person_id, position_id, parsed_views
