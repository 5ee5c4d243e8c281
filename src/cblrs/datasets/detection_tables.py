"""Detection files: MOT and AI City tables of boxes, read frame by frame.

Each reader yields :class:`SourceFrame` objects — frame number, capture time relative to the
start of the recording and the frame's boxes — in frame order, with empty frames filled in:

* :func:`mot_source` — a MOT-format detections file (``frame,id,x,y,w,h,conf,...``);
* :func:`aicity_source` — an AI City format file (``camera obj frame x y w h ...``).

They are file formats, so they live with the other readers; an edge camera
(:mod:`cblrs.runtime.camera.sources`) replays them as one of its sources.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cblrs.datasets.images import UnusableImage
from cblrs.detections import Detections
from cblrs.errors import CblrsError, DatasetError


@dataclass(frozen=True, eq=False)
class SourceFrame:
    """One captured frame's detections.

    Attributes:
        frame: frame number in the source's own numbering.
        timestamp: capture time in seconds since the start of the recording, or ``None`` when
            the frame is live (the camera node then stamps it with the wall clock).
        detections: the frame's boxes.
        unusable: the frame's image file could not be used (empty, cut short, undecodable):
            the frame is skipped, counted and logged by the camera node; ``detections`` is
            then empty and means nothing.
    """

    frame: int
    timestamp: float | None
    detections: Detections
    unusable: UnusableImage | None = None


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
