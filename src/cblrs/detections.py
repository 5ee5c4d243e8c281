"""Core record types shared by the pipeline stages, as named numpy columns.

* :class:`Detections` — boxes of one camera frame (what a detector gives).
* :class:`CameraMessage` — what a camera sends: boxes and reference *colours*, never pixels
  of the image (the paper's message M).
* :class:`Tracks` — the matcher's output, one row per (frame, track), in world metres.

Every column is vectorised over N rows and validated on construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

CLASS_NAMES: tuple[str, ...] = ("person", "car", "bicycle", "motorcycle", "bus", "truck")
"""Class ids used on the wire: the index into this tuple."""

CLASS_SIZE_PRIORS: dict[str, tuple[float, float, float]] = {
    "person": (0.5, 0.5, 1.75),
    "car": (4.5, 1.8, 1.5),
    "bicycle": (1.8, 0.6, 1.7),
    "motorcycle": (2.1, 0.8, 1.5),
    "bus": (12.0, 2.55, 3.2),
    "truck": (8.0, 2.5, 3.5),
}
"""Class-typical length, width, height (metres): a mid-size car, a bicycle or motorcycle with
its rider, a city bus (12 m, 2.55 m: the EU's maximum width), a rigid truck. One table for the
synthetic world's boxes, geometric targeting and the matcher's footprint stage (here, where
the matcher finds it without importing the datasets)."""

MESSAGE_SCHEMA = "cblrs.detections/1"

SURE_CONFIDENCE = 0.5
"""Detector score from which a box is one the detector is sure of (ByteTrack's split between
high- and low-confidence boxes). Below it a box is doubtful: the fusion tracker accepts it only
where a track or another camera confirms it (``high_confidence``), and at the camera it may
not hide a sure box's feet (:func:`cblrs.edge.feet_hidden`)."""


def class_id_of(name: str) -> int:
    """The index of a class name in :data:`CLASS_NAMES`; ValueError naming the known ones."""
    try:
        return CLASS_NAMES.index(name)
    except ValueError:
        raise ValueError(f"unknown class {name!r}; known: {', '.join(CLASS_NAMES)}") from None


def _column(value: Any, dtype: Any, shape: tuple[int | None, ...], name: str) -> NDArray:
    # Every column here is (N,) or (N, k): only the first size is free, so the check is one
    # tuple comparison (this runs for every column of every message, window and table).
    array = np.asarray(value, dtype=dtype)
    if array.ndim != len(shape) or array.shape[1:] != shape[1:]:
        wanted = "(" + ", ".join("N" if size is None else str(size) for size in shape) + ")"
        raise ValueError(f"{name} must have shape {wanted}, got {array.shape}")
    return array


class _Columns:
    """Shared behaviour of the column dataclasses: length checks, masks, concatenation."""

    _row_columns: tuple[str, ...] = ()

    def _validate_lengths(self) -> None:
        sizes = [len(getattr(self, name)) for name in self._row_columns]
        if sizes.count(sizes[0]) != len(sizes):
            lengths = dict(zip(self._row_columns, sizes, strict=True))
            raise ValueError(f"columns of {type(self).__name__} differ in length: {lengths}")

    def __len__(self) -> int:
        return len(getattr(self, self._row_columns[0]))

    def __getitem__(self, index: Any):
        """Rows selected by a boolean mask, an index array or a slice."""
        if isinstance(index, int | np.integer):
            index = [int(index)]
        changes = {name: getattr(self, name)[index] for name in self._row_columns}
        return replace(self, **changes)  # type: ignore[type-var]


@dataclass(frozen=True, eq=False)
class Detections(_Columns):
    """Boxes of one camera frame.

    Attributes:
        xyxy: (N, 4) float64 pixels, (x_min, y_min, x_max, y_max).
        confidence: (N,) float64 in 0..1.
        class_id: (N,) int64, index into :data:`CLASS_NAMES`.
        object_id: (N,) int64 ground-truth identity when known (datasets), else -1.
    """

    xyxy: NDArray[np.float64]
    confidence: NDArray[np.float64] = field(default=None)  # type: ignore[arg-type]
    class_id: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]
    object_id: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]

    _row_columns = ("xyxy", "confidence", "class_id", "object_id")

    def __post_init__(self) -> None:
        xyxy = _column(self.xyxy, np.float64, (None, 4), "xyxy")
        count = len(xyxy)
        object.__setattr__(self, "xyxy", xyxy)
        # Defaults are made only for the columns not given (data sets give every column, for
        # thousands of boxes lists).
        for name, dtype, default in (("confidence", np.float64, 1.0),
                                     ("class_id", np.int64, 0), ("object_id", np.int64, -1)):
            value = getattr(self, name)
            if value is None:
                value = np.full(count, default, dtype=dtype)
            object.__setattr__(self, name, _column(value, dtype, (None,), name))
        self._validate_lengths()

    @classmethod
    def empty(cls) -> Detections:
        """No detections (every column of length 0)."""
        return cls(xyxy=np.zeros((0, 4)))

    @classmethod
    def concatenate(cls, parts: list[Detections]) -> Detections:
        """All rows of ``parts``, in order, as one object."""
        if not parts:
            return cls.empty()
        return cls(
            **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)}
        )


@dataclass(frozen=True, eq=False)
class CameraMessage(_Columns):
    """One camera frame as sent to the matcher (the paper's message M).

    Only boxes and reference colours leave the camera; there is deliberately no field that
    could carry image data.

    Attributes:
        camera_id: the sending camera.
        sequence: per-camera message counter (for de-duplication), starting at 0.
        timestamp: capture time in seconds (any epoch shared by all cameras).
        frame: camera frame number.
        xyxy: (N, 4) float64 pixel boxes.
        confidence: (N,) float64.
        class_id: (N,) int64, index into :data:`CLASS_NAMES`.
        colour: (N, 3) int64 reference colours at the target pixels; B = 0 means the target
            saw no plane.
    """

    camera_id: str
    sequence: int
    timestamp: float
    frame: int
    xyxy: NDArray[np.float64]
    confidence: NDArray[np.float64]
    class_id: NDArray[np.int64]
    colour: NDArray[np.int64]
    schema: str = MESSAGE_SCHEMA

    _row_columns = ("xyxy", "confidence", "class_id", "colour")

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyxy", _column(self.xyxy, np.float64, (None, 4), "xyxy"))
        object.__setattr__(
            self, "confidence", _column(self.confidence, np.float64, (None,), "confidence")
        )
        object.__setattr__(self, "class_id", _column(self.class_id, np.int64, (None,), "class_id"))
        object.__setattr__(self, "colour", _column(self.colour, np.int64, (None, 3), "colour"))
        self._validate_lengths()

    @classmethod
    def empty(cls, camera_id: str, sequence: int, timestamp: float, frame: int) -> CameraMessage:
        """A message of a frame without detections (cameras send these too)."""
        return cls(
            camera_id,
            sequence,
            timestamp,
            frame,
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros(0, np.int64),
            np.zeros((0, 3), np.int64),
        )


@dataclass(frozen=True, eq=False)
class Tracks(_Columns):
    """Tracker output, one row per (frame, track).

    Attributes:
        frame: (N,) int64 frame number (the dataset's own numbering).
        timestamp: (N,) float64 seconds.
        track_id: (N,) int64 global identity.
        world_xy: (N, 2) float64 metres.
        camera_id: (N,) int64 index of the camera whose box is reported (-1 if none).
        xyxy: (N, 4) float64 that camera's box (NaN if none).
        class_id: (N,) int64 the track's class, index into :data:`CLASS_NAMES` (-1 unknown).
            Matchers fill it from their detections' classes; the AI City text format has no
            class field, so :func:`cblrs.datasets.write_tracks` keeps it in a sidecar file.
    """

    frame: NDArray[np.int64]
    timestamp: NDArray[np.float64]
    track_id: NDArray[np.int64]
    world_xy: NDArray[np.float64]
    camera_id: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]
    xyxy: NDArray[np.float64] = field(default=None)  # type: ignore[arg-type]
    class_id: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]

    _row_columns = (
        "frame", "timestamp", "track_id", "world_xy", "camera_id", "xyxy", "class_id",
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", _column(self.frame, np.int64, (None,), "frame"))
        object.__setattr__(
            self, "timestamp", _column(self.timestamp, np.float64, (None,), "timestamp")
        )
        object.__setattr__(self, "track_id", _column(self.track_id, np.int64, (None,), "track_id"))
        object.__setattr__(
            self, "world_xy", _column(self.world_xy, np.float64, (None, 2), "world_xy")
        )
        count = len(self.frame)
        camera_id = np.full(count, -1) if self.camera_id is None else self.camera_id
        xyxy = np.full((count, 4), np.nan) if self.xyxy is None else self.xyxy
        object.__setattr__(self, "camera_id", _column(camera_id, np.int64, (None,), "camera_id"))
        object.__setattr__(self, "xyxy", _column(xyxy, np.float64, (None, 4), "xyxy"))
        class_id = np.full(count, -1) if self.class_id is None else self.class_id
        object.__setattr__(self, "class_id", _column(class_id, np.int64, (None,), "class_id"))
        self._validate_lengths()

    @classmethod
    def empty(cls) -> Tracks:
        """No track rows (every column of length 0)."""
        return cls(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 2)))

    @classmethod
    def concatenate(cls, parts: list[Tracks]) -> Tracks:
        """All rows of ``parts``, in order, as one object."""
        if not parts:
            return cls.empty()
        return cls(
            **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)}
        )
