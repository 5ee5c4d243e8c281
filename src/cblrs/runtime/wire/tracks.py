"""``cblrs.tracks/1``: a matcher's track updates on ``cblrs/<plane>/tracks``, and the
linker's global ones on ``cblrs/0/tracks`` (plane 0: the whole site).

A global update's rows carry the global id in ``track`` and where it came from:
``source_plane`` (the plane whose matcher saw it) and ``source_track`` (that matcher's id).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Any

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES, Tracks
from cblrs.runtime.wire.common import (
    CLASS_IDS,
    MAX_INT,
    MAX_TRACK_ROWS,
    TRACKS_SCHEMA,
    CameraId,
    ClassName,
    Count,
    PlaneId,
    RejectedMessage,
    RejectReason,
    SitePlaneId,
    _decode_typed,
)


class WireTrack(msgspec.Struct, forbid_unknown_fields=True):
    """One track row on the wire."""

    frame: Count
    timestamp: float
    track: Annotated[int, msgspec.Meta(ge=-MAX_INT, le=MAX_INT)]
    world_xy: tuple[float, float]
    camera: Annotated[int, msgspec.Meta(ge=-1, le=MAX_INT)] = -1
    box: tuple[float, float, float, float] | None = None
    class_name: ClassName | None = msgspec.field(default=None, name="class")
    """The track's class (a name of :data:`~cblrs.detections.CLASS_NAMES`); absent: unknown."""
    source_plane: PlaneId | None = None
    """Global rows (plane 0): the plane whose matcher gave the row."""
    source_track: Annotated[int, msgspec.Meta(ge=-MAX_INT, le=MAX_INT)] | None = None
    """Global rows (plane 0): that matcher's track id."""


class WireTracks(msgspec.Struct, forbid_unknown_fields=True):
    """A ``cblrs.tracks/1`` payload."""

    schema: str
    plane: SitePlaneId
    sequence: Count
    tracks: Annotated[list[WireTrack], msgspec.Meta(max_length=MAX_TRACK_ROWS)]
    cameras: Annotated[list[CameraId], msgspec.Meta(max_length=1000)] = msgspec.field(
        default_factory=list
    )
    timestamp: float | None = None
    corrected_from: float | None = None
    """A correction (late messages re-tracked): these rows replace every row of the plane
    after this time, seconds, that earlier updates carried."""


@dataclass(frozen=True)
class TracksUpdate:
    """A decoded track update.

    Attributes:
        plane_id: the plane the tracks are on.
        sequence: the matcher's update counter.
        tracks: the rows (``camera_id`` indexes ``cameras`` when that is given).
        cameras: camera ids, in the order ``Tracks.camera_id`` refers to them (may be empty).
        timestamp: the update's time, seconds: the matcher has tracked everything captured
            up to it (an empty update says no track is there at that time); None if not said.
        source_plane: global updates (plane 0): (N,) int64 the plane of each row, else None.
        source_track: global updates: (N,) int64 that plane's track id, else None.
        corrected_from: a correction: the rows replace those after this time that earlier
            updates carried (late messages were re-tracked); None: a new update.
    """

    plane_id: int
    sequence: int
    tracks: Tracks
    cameras: tuple[str, ...] = field(default=())
    timestamp: float | None = None
    source_plane: np.ndarray | None = None
    source_track: np.ndarray | None = None
    corrected_from: float | None = None


def encode_tracks(
    tracks: Tracks,
    plane_id: int,
    *,
    sequence: int = 0,
    cameras: list[str] | None = None,
    timestamp: float | None = None,
    source_plane: np.ndarray | None = None,
    source_track: np.ndarray | None = None,
    corrected_from: float | None = None,
) -> bytes:
    """Serialise track rows for ``cblrs/<plane>/tracks`` (schema ``cblrs.tracks/1``).

    Args:
        tracks: rows to publish; NaN boxes are sent as ``null``.
        plane_id: the plane (0: the site's global tracks).
        sequence: the matcher's update counter.
        cameras: camera ids that ``tracks.camera_id`` indexes (optional).
        timestamp: the update's time (the released group's capture time; optional).
        source_plane, source_track: global rows: (N,) where each came from (both or neither).
        corrected_from: a correction of the rows after this time (see :class:`TracksUpdate`;
            -inf: of every row).

    Raises:
        RejectedMessage: non-finite positions or times, or too many rows.
    """
    if len(tracks) > MAX_TRACK_ROWS:
        raise RejectedMessage(
            RejectReason.OVERSIZED, f"{len(tracks)} rows, at most {MAX_TRACK_ROWS} per update"
        )
    if not (np.isfinite(tracks.world_xy).all() and np.isfinite(tracks.timestamp).all()):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "track positions must be finite")
    if (source_plane is None) != (source_track is None):
        raise ValueError("give source_plane and source_track together")
    sources = (
        zip(np.asarray(source_plane).tolist(), np.asarray(source_track).tolist(), strict=True)
        if source_plane is not None and source_track is not None else None
    )
    rows = []
    for frame, timestamp, track_id, world_xy, camera, box, class_id in zip(
        tracks.frame.tolist(),
        tracks.timestamp.tolist(),
        tracks.track_id.tolist(),
        tracks.world_xy.tolist(),
        tracks.camera_id.tolist(),
        tracks.xyxy.tolist(),
        tracks.class_id.tolist(),
        strict=True,
    ):
        row: dict[str, Any] = {
            "frame": frame,
            "timestamp": timestamp,
            "track": track_id,
            "world_xy": world_xy,
            "camera": camera,
        }
        if all(math.isfinite(value) for value in box):
            row["box"] = box
        if 0 <= class_id < len(CLASS_NAMES):
            row["class"] = CLASS_NAMES[class_id]
        if sources is not None:
            row["source_plane"], row["source_track"] = next(sources)
        rows.append(row)
    document = {
        "schema": TRACKS_SCHEMA,
        "plane": plane_id,
        "sequence": sequence,
        "tracks": rows,
        "cameras": list(cameras or []),
    }
    if timestamp is not None:
        if not math.isfinite(timestamp):
            raise RejectedMessage(RejectReason.INVALID_VALUE, "the update's time must be finite")
        document["timestamp"] = float(timestamp)
    if corrected_from is not None:
        if math.isnan(corrected_from) or corrected_from == math.inf:
            raise RejectedMessage(RejectReason.INVALID_VALUE,
                                  "the corrected time must be finite (or -inf: every row)")
        # JSON has no infinity: a correction of everything is sent from time 0.
        document["corrected_from"] = max(0.0, float(corrected_from))
    try:
        msgspec.convert(document, WireTracks)
    except msgspec.ValidationError as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    return msgspec.json.encode(document)


def decode_tracks(payload: bytes, *, max_bytes: int = 8 * 1024 * 1024) -> TracksUpdate:
    """Decode a ``cblrs.tracks/1`` payload.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if len(payload) > max_bytes:
        raise RejectedMessage(
            RejectReason.OVERSIZED, f"payload of {len(payload)} bytes exceeds {max_bytes}"
        )
    wire = _decode_typed(payload, WireTracks, TRACKS_SCHEMA)
    rows = wire.tracks
    tracks = Tracks(
        frame=np.array([row.frame for row in rows], dtype=np.int64),
        timestamp=np.array([row.timestamp for row in rows], dtype=np.float64),
        track_id=np.array([row.track for row in rows], dtype=np.int64),
        world_xy=np.array([row.world_xy for row in rows], dtype=np.float64).reshape(-1, 2),
        camera_id=np.array([row.camera for row in rows], dtype=np.int64),
        xyxy=np.array(
            [row.box if row.box is not None else (math.nan,) * 4 for row in rows],
            dtype=np.float64,
        ).reshape(-1, 4),
        class_id=np.array(
            [-1 if row.class_name is None else CLASS_IDS.get(row.class_name, -2) for row in rows],
            dtype=np.int64,
        ),
    )
    if not (np.isfinite(tracks.world_xy).all() and np.isfinite(tracks.timestamp).all()):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "track positions must be finite")
    if (tracks.class_id == -2).any():
        raise RejectedMessage(
            RejectReason.INVALID_VALUE, f"unknown track class; known: {', '.join(CLASS_NAMES)}"
        )
    if wire.timestamp is not None and not math.isfinite(wire.timestamp):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "the update's time must be finite")
    sources = [(row.source_plane, row.source_track) for row in rows]
    known = [plane is not None and track is not None for plane, track in sources]
    if any(known) and not all(known):
        raise RejectedMessage(RejectReason.MISSING_FIELD,
                              "every row of a global update needs source_plane and source_track")
    source_plane = source_track = None
    if rows and all(known):
        source_plane = np.array([plane for plane, _ in sources], dtype=np.int64)
        source_track = np.array([track for _, track in sources], dtype=np.int64)
    if wire.corrected_from is not None and not math.isfinite(wire.corrected_from):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "the corrected time must be finite")
    return TracksUpdate(wire.plane, wire.sequence, tracks, tuple(wire.cameras), wire.timestamp,
                        source_plane, source_track, wire.corrected_from)
