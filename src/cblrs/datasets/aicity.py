"""The AI City Challenge 2024 (track 1) text format for tracks and ground truth.

One row per frame and track, whitespace separated::

    <camera_id> <obj_id> <frame_id> <xmin> <ymin> <width> <height> <xworld> <yworld>

``camera_id``, ``obj_id`` and ``frame_id`` are integers; the box is in pixels
(converted from/to :class:`cblrs.detections.Tracks`' ``xyxy``), the world position in metres.
Rows are written in the order given and read back in file order: the AI City evaluation
counts only the first row of each (frame, id), so the order matters.

A track without a box (``xyxy`` all NaN, e.g. a position fused from several cameras) is
written with the box ``-1 -1 -1 -1`` and read back as NaN. A track without a camera has
``camera_id`` -1.

The format carries no time: :func:`read_tracks` sets ``timestamp`` to the frame number (or to
``frame / frames_per_second`` when the rate is given); callers that know the dataset's timing
map frames to seconds themselves.

Nor does it carry a class. So that the file stays exactly what TrackEval and the AI City tools
read, :func:`write_tracks` puts what the format lacks — each track's class and the frame rate,
or, for tracks whose frames have no fixed rate (a live matcher's), the capture time of every
frame (or row) — in a JSON sidecar ``<file>.meta.json`` (schema ``cblrs.tracks-meta/1``) next
to it, with the SHA-256 of the tracks file so that a sidecar left over from another file is
refused, not trusted; :func:`read_track_metadata` reads it, :func:`apply_track_metadata` fills
``Tracks.class_id`` and :func:`metadata_timestamps` gives the rows' times.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CLASS_NAMES, Tracks, class_id_of
from cblrs.errors import DatasetError

logger = logging.getLogger(__name__)

COLUMNS = (
    "camera_id", "obj_id", "frame_id", "xmin", "ymin", "width", "height", "xworld", "yworld",
)
_INTEGER_COLUMNS = (0, 1, 2)
_NO_BOX = -1.0


def write_tracks(
    path: str | Path,
    tracks: Tracks,
    frames_per_second: float | None = None,
    keep_timestamps: bool = False,
) -> None:
    """Write tracks as an AI City 2024 text file (rows in the given order).

    When some ``class_id`` is known, ``frames_per_second`` is given or ``keep_timestamps`` is
    set, a sidecar ``<path>.meta.json`` keeps them (see the module docstring); otherwise a
    sidecar left from an earlier file of that name is removed.

    Args:
        path: the output file (overwritten).
        tracks: the rows; ``camera_id``, ``track_id``, ``frame``, ``xyxy`` (pixels, NaN for
            no box) and ``world_xy`` (metres) are written, ``timestamp`` only to the sidecar
            with ``keep_timestamps``.
        frames_per_second: the rate of the frame numbers (``timestamp = frame / rate``).
        keep_timestamps: keep each row's ``timestamp`` (seconds) in the sidecar: one per frame
            number when each frame has one time, else one per row.

    Raises:
        DatasetError: a world position is not finite, or the file cannot be written.
    """
    path = Path(path)
    if not np.all(np.isfinite(tracks.world_xy)):
        bad = int(np.flatnonzero(~np.isfinite(tracks.world_xy).all(axis=1))[0])
        raise DatasetError(
            f"cannot write {path}: row {bad} (frame {int(tracks.frame[bad])}, track "
            f"{int(tracks.track_id[bad])}) has a non-finite world position."
        )
    xyxy = tracks.xyxy
    has_box = np.isfinite(xyxy).all(axis=1)
    boxes = np.full((len(tracks), 4), _NO_BOX)
    boxes[has_box, 0:2] = xyxy[has_box, 0:2]
    boxes[has_box, 2:4] = xyxy[has_box, 2:4] - xyxy[has_box, 0:2]
    lines = [
        f"{camera} {track} {frame} {x:.2f} {y:.2f} {width:.2f} {height:.2f} {wx:.4f} {wy:.4f}\n"
        for camera, track, frame, (x, y, width, height), (wx, wy) in zip(
            tracks.camera_id.tolist(),
            tracks.track_id.tolist(),
            tracks.frame.tolist(),
            boxes.tolist(),
            tracks.world_xy.tolist(),
            strict=True,
        )
    ]
    text = "".join(lines)
    try:
        # People's positions: readable by the owner only (also when the file existed).
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(descriptor, "w") as handle:
            handle.write(text)
        os.chmod(path, 0o600)
    except OSError as error:
        raise DatasetError(f"cannot write {path}: {error.strerror or error}.") from None
    logger.debug("wrote %d rows to %s", len(tracks), path)
    _write_metadata(path, text, tracks, frames_per_second, keep_timestamps)


METADATA_SCHEMA = "cblrs.tracks-meta/1"


@dataclass(frozen=True)
class TrackMetadata:
    """What the AI City format cannot hold, read from a tracks file's sidecar.

    Attributes:
        frames_per_second: rate of the file's frame numbers (None: unknown).
        classes: track id -> class id (index into :data:`CLASS_NAMES`), for tracks whose
            class is known.
        frame_seconds: frame number -> capture time (seconds), when the sidecar keeps one
            time per frame.
        row_seconds: (N,) capture time of each row, when it keeps one per row.
    """

    frames_per_second: float | None
    classes: dict[int, int]
    frame_seconds: dict[int, float] | None = None
    row_seconds: NDArray[np.float64] | None = None

    @property
    def has_timestamps(self) -> bool:
        """The sidecar keeps the rows' capture times."""
        return self.frame_seconds is not None or self.row_seconds is not None


def metadata_path(path: str | Path) -> Path:
    """The sidecar of a tracks file: ``tracks.txt`` -> ``tracks.txt.meta.json``."""
    path = Path(path)
    return path.with_name(path.name + ".meta.json")


def track_classes(tracks: Tracks) -> dict[int, int]:
    """Each track's class: the most frequent known ``class_id`` of its rows (ties: lowest).

    Tracks whose rows all have class -1 are left out.
    """
    known = tracks.class_id >= 0
    if not known.any():
        return {}
    ids, classes = tracks.track_id[known], tracks.class_id[known]
    pairs, counts = np.unique(np.stack([ids, classes], axis=1), axis=0, return_counts=True)
    # Sort by track, then count descending, then class ascending; keep each track's first.
    order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
    pairs = pairs[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    return {int(track): int(class_id) for track, class_id in pairs[first].tolist()}


def _write_metadata(
    path: Path,
    text: str,
    tracks: Tracks,
    frames_per_second: float | None,
    keep_timestamps: bool = False,
) -> None:
    sidecar = metadata_path(path)
    classes = track_classes(tracks)
    if frames_per_second is None and not classes and not keep_timestamps:
        sidecar.unlink(missing_ok=True)
        return
    if frames_per_second is not None and not frames_per_second > 0:
        raise DatasetError(f"frames per second must be positive, got {frames_per_second}.")
    document = {
        "schema": METADATA_SCHEMA,
        "tracks_file": path.name,
        "rows": len(tracks),
        "sha256": hashlib.sha256(text.encode()).hexdigest(),
        "frames_per_second": frames_per_second,
        "classes": {str(track): CLASS_NAMES[class_id] for track, class_id in classes.items()},
    }
    if keep_timestamps:
        document["timestamps"] = _timestamps_document(tracks)
    try:
        # Owner only, as its tracks file: it says how many rows and which tracks it holds.
        descriptor = os.open(sidecar, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(descriptor, "w") as handle:
            handle.write(json.dumps(document, indent=1) + "\n")
        os.chmod(sidecar, 0o600)
    except OSError as error:
        raise DatasetError(f"cannot write {sidecar}: {error.strerror or error}.") from None


def _timestamps_document(tracks: Tracks) -> dict[str, list[Any]]:
    """``{"frames": [...], "seconds": [...]}`` when every frame number has one time, else
    ``{"rows": [...]}`` (JSON keeps a float exactly)."""
    frames, first = np.unique(tracks.frame, return_index=True)
    seconds = tracks.timestamp[first]
    position = np.searchsorted(frames, tracks.frame)
    if np.array_equal(seconds[position], tracks.timestamp):
        return {"frames": frames.tolist(), "seconds": seconds.tolist()}
    return {"rows": tracks.timestamp.tolist()}


def _read_timestamps(
    document: dict[str, Any], rows: int
) -> tuple[dict[int, float] | None, NDArray[np.float64] | None]:
    times = document.get("timestamps")
    if times is None:
        return None, None
    if not isinstance(times, dict):
        raise ValueError("timestamps must be an object")
    if "rows" in times:
        row_seconds = np.asarray(times["rows"], dtype=np.float64)
        if row_seconds.shape != (rows,) or not np.isfinite(row_seconds).all():
            raise ValueError(f"timestamps.rows must hold {rows} finite numbers")
        return None, row_seconds
    if "frames" not in times or "seconds" not in times:
        raise ValueError("timestamps must hold rows, or frames and seconds")
    frames, seconds = list(times["frames"]), [float(value) for value in times["seconds"]]
    if len(frames) != len(seconds):
        raise ValueError("timestamps.frames and timestamps.seconds differ in length")
    return dict(zip((int(frame) for frame in frames), seconds, strict=True)), None


def metadata_timestamps(
    tracks: Tracks, metadata: TrackMetadata | None
) -> NDArray[np.float64] | None:
    """(N,) the rows' capture times kept in the sidecar, or None when it keeps none.

    Raises:
        DatasetError: the sidecar has no time for a frame of ``tracks``.
    """
    if metadata is None:
        return None
    if metadata.row_seconds is not None:
        return metadata.row_seconds.copy()
    if metadata.frame_seconds is None:
        return None
    try:
        return np.array([metadata.frame_seconds[frame] for frame in tracks.frame.tolist()],
                        dtype=np.float64)
    except KeyError as error:
        raise DatasetError(f"the tracks' sidecar has no time for frame {error.args[0]}.") from None


def read_track_metadata(path: str | Path) -> TrackMetadata | None:
    """The sidecar of a tracks file, or None when there is none.

    Raises:
        DatasetError: the sidecar is malformed, or was written for a different tracks file
            (its SHA-256 does not match), so its classes cannot be trusted.
    """
    path = Path(path)
    sidecar = metadata_path(path)
    if not sidecar.exists():
        return None
    try:
        document: Any = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"cannot read {sidecar}: {error}.") from None
    if not isinstance(document, dict) or document.get("schema") != METADATA_SCHEMA:
        raise DatasetError(f"{sidecar} is not a {METADATA_SCHEMA} sidecar.")
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as error:
        raise DatasetError(f"cannot read tracks file {path}: {error.strerror or error}.") from None
    if document.get("sha256") != digest:
        raise DatasetError(
            f"{sidecar} belongs to another version of {path.name} (the file changed since); "
            "delete the sidecar or write the tracks again."
        )
    try:
        rate = document.get("frames_per_second")
        rate = None if rate is None else float(rate)
        classes = {
            int(track): class_id_of(str(name))
            for track, name in dict(document.get("classes") or {}).items()
        }
        frame_seconds, row_seconds = _read_timestamps(document, int(document.get("rows", -1)))
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{sidecar}: {error}.") from None
    return TrackMetadata(frames_per_second=rate, classes=classes, frame_seconds=frame_seconds,
                         row_seconds=row_seconds)


def apply_track_metadata(tracks: Tracks, metadata: TrackMetadata | None) -> Tracks:
    """``tracks`` with ``class_id`` set from the sidecar's classes (others left as they are)."""
    if metadata is None or not metadata.classes or len(tracks) == 0:
        return tracks
    ids = np.array(sorted(metadata.classes), dtype=np.int64)
    classes = np.array([metadata.classes[int(track)] for track in ids], dtype=np.int64)
    position = np.clip(np.searchsorted(ids, tracks.track_id), 0, len(ids) - 1)
    found = ids[position] == tracks.track_id
    class_id = np.where(found, classes[position], tracks.class_id)
    return replace(tracks, class_id=class_id)


def read_tracks(path: str | Path, frames_per_second: float | None = None) -> Tracks:
    """Read an AI City 2024 text file of tracks or ground truth.

    Args:
        path: the file; blank lines (such as a trailing one) are skipped.
        frames_per_second: when given, ``timestamp = frame / frames_per_second``; otherwise the
            file has no timing and ``timestamp`` is the frame number as given.

    Returns:
        The rows in file order; boxes ``-1 -1 -1 -1`` become NaN ``xyxy``.

    Raises:
        DatasetError: the file is missing, or a row (named ``file:line``) has the wrong
            number of columns, a non-numeric or non-finite value, a fractional id or a
            negative frame number.
    """
    path = Path(path)
    if frames_per_second is not None and not frames_per_second > 0:
        raise DatasetError(f"frames per second must be positive, got {frames_per_second}.")
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"tracks file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"cannot read tracks file {path}: {error}.") from None
    if not text.strip():
        return Tracks.empty()
    values = _parse(text, path)
    for column in _INTEGER_COLUMNS:
        fractional = values[:, column] != np.round(values[:, column])
        if fractional.any():
            _raise_at_row(text, path, int(np.flatnonzero(fractional)[0]),
                          f"{COLUMNS[column]} must be an integer")
    negative = values[:, 2] < 0
    if negative.any():
        # A frame number counts frames from the start of a recording; a negative one is a
        # shifted or corrupted file, and its rows would be timed before the recording began.
        _raise_at_row(text, path, int(np.flatnonzero(negative)[0]),
                      "frame_id must not be negative")
    frame = values[:, 2].astype(np.int64)
    x, y, width, height = values[:, 3], values[:, 4], values[:, 5], values[:, 6]
    xyxy = np.stack([x, y, x + width, y + height], axis=1)
    no_box = (values[:, 3:7] == _NO_BOX).all(axis=1)
    xyxy[no_box] = np.nan
    timestamp = frame.astype(np.float64)
    if frames_per_second is not None:
        timestamp = timestamp / frames_per_second
    return Tracks(
        frame=frame,
        timestamp=timestamp,
        track_id=values[:, 1].astype(np.int64),
        world_xy=values[:, 7:9].copy(),
        camera_id=values[:, 0].astype(np.int64),
        xyxy=xyxy,
    )


def _parse(text: str, path: Path) -> NDArray[np.float64]:
    """(N, 9) float64 values of the non-blank rows; errors name the offending line."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2, comments=None)
    except (ValueError, UserWarning):
        values = None
    if values is None or values.shape[1] != len(COLUMNS):
        _raise_first_bad_line(text, path)
    assert values is not None
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        _raise_at_row(text, path, int(np.flatnonzero(~finite)[0]), "a value is not finite")
    return values


def _raise_first_bad_line(text: str, path: Path) -> None:
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != len(COLUMNS):
            raise DatasetError(
                f"{path}:{number}: expected {len(COLUMNS)} columns ({' '.join(COLUMNS)}), "
                f"got {len(tokens)}."
            )
        for name, token in zip(COLUMNS, tokens, strict=True):
            try:
                float(token)
            except ValueError:
                raise DatasetError(f"{path}:{number}: {name} {token!r} is not a number.") from None
    raise DatasetError(f"{path} is not a valid AI City tracks file.")


def _raise_at_row(text: str, path: Path, row: int, problem: str) -> None:
    """Raise for the ``row``-th non-blank line (0-based), naming its line number."""
    seen = -1
    for number, line in enumerate(text.splitlines(), start=1):
        if line.strip():
            seen += 1
            if seen == row:
                raise DatasetError(f"{path}:{number}: {problem} in {line.strip()!r}.")
    raise DatasetError(f"{path}: row {row + 1}: {problem}.")
