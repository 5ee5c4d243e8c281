"""What travels over MQTT: versioned JSON messages, decoded into typed structs and validated.

Three payloads, each JSON (readable with ``mosquitto_sub -v``) and tagged with a schema:

* ``cblrs.detections/1`` on ``cblrs/<plane>/<camera>/detections`` — one camera frame::

      {"schema": "cblrs.detections/1", "camera": "CVLab1", "sequence": 41,
       "timestamp": 1700000000.25, "frame": 5, "plane": 1,
       "detections": [{"class": "person", "confidence": 0.91,
                       "box": [10.0, 20.0, 50.0, 120.0], "colour": [1200, 33000, 1]}]}

  No field can carry image data: strings are a fixed schema tag, a bounded camera id and a
  class name from :data:`~cblrs.detections.CLASS_NAMES`; everything else is a number; unknown
  fields are refused and the payload size is bounded.
* ``cblrs.tracks/1`` on ``cblrs/<plane>/tracks`` — track updates of a matcher, one per
  released group, empty ones too (no objects is information: a viewer drops stale marks);
  each row may name its ``class``.
* ``cblrs.status/1`` on the status topics — retained availability ("online"/"offline").

The receiver decodes with :func:`decode_message` (or :meth:`ValidationPolicy.decode`), which
raises :class:`RejectedMessage` carrying a :class:`RejectReason` for anything it refuses, and
nothing else.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Annotated, Any, Literal, TypeVar

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.errors import CblrsError
from cblrs.runtime.topics import ID_PATTERN, MAX_ID_LENGTH, MAX_PLANE_ID

_T = TypeVar("_T")

DETECTIONS_SCHEMA = "cblrs.detections/1"
TRACKS_SCHEMA = "cblrs.tracks/1"
STATUS_SCHEMA = "cblrs.status/1"

MAX_DETECTIONS = 1000
"""Most detections one message may hold."""
MAX_TRACK_ROWS = 10000
"""Most rows one track update may hold."""
DEFAULT_MAX_BYTES = 256 * 1024
"""Default payload limit: :data:`MAX_DETECTIONS` detections at up to ~200 bytes each."""
DEFAULT_MAX_AGE_S = 24 * 3600.0
"""Default oldest accepted capture time: a day, so a matcher down for hours still catches up."""
DEFAULT_MAX_FUTURE_S = 60.0
"""Default tolerance for camera clocks ahead of the matcher's."""
MAX_INT = 2**53
"""Integers on the wire stay exactly representable in a double (JavaScript readers)."""

CLASS_IDS = {name: index for index, name in enumerate(CLASS_NAMES)}
"""Class id of each class name on the wire."""

CameraId = Annotated[
    str, msgspec.Meta(min_length=1, max_length=MAX_ID_LENGTH, pattern=ID_PATTERN)
]
Count = Annotated[int, msgspec.Meta(ge=0, le=MAX_INT)]
PlaneId = Annotated[int, msgspec.Meta(ge=1, le=MAX_PLANE_ID)]
ClassName = Annotated[str, msgspec.Meta(max_length=32)]


class RejectReason(Enum):
    """Why a received payload was refused (the matcher counts rejections by reason)."""

    MALFORMED_JSON = "malformed_json"
    WRONG_SCHEMA = "wrong_schema"
    MISSING_FIELD = "missing_field"
    UNKNOWN_FIELD = "unknown_field"
    INVALID_VALUE = "invalid_value"
    OVERSIZED = "oversized"
    COLOUR_OUT_OF_RANGE = "colour_out_of_range"
    UNKNOWN_CAMERA = "unknown_camera"
    TOPIC_MISMATCH = "topic_mismatch"
    TOO_OLD = "too_old"
    IN_FUTURE = "in_future"


class RejectedMessage(CblrsError):
    """A payload that fails validation.

    Attributes:
        reason: the category, for counters.
        detail: one sentence saying what was wrong.
    """

    def __init__(self, reason: RejectReason, detail: str):
        super().__init__(f"{reason.value}: {detail}")
        self.reason = reason
        self.detail = detail

    def __reduce__(self):  # keep picklable (multiprocessing, logging handlers)
        return (type(self), (self.reason, self.detail))


class WireDetection(msgspec.Struct, forbid_unknown_fields=True):
    """One detection on the wire."""

    class_name: ClassName = msgspec.field(name="class")
    confidence: float
    box: tuple[float, float, float, float]
    colour: tuple[int, int, int]


class WireMessage(msgspec.Struct, forbid_unknown_fields=True):
    """A ``cblrs.detections/1`` payload."""

    schema: str
    camera: CameraId
    sequence: Count
    timestamp: float
    frame: Count
    plane: PlaneId
    detections: Annotated[list[WireDetection], msgspec.Meta(max_length=MAX_DETECTIONS)]


@dataclass(frozen=True)
class ValidationPolicy:
    """What a receiver accepts; the matcher service holds one.

    Attributes:
        known_cameras: camera ids allowed to send; None accepts any valid id.
        bits: bits per colour channel of the reference images (8 or 16).
        max_age_s: oldest accepted capture time, seconds before ``now`` (``math.inf``: any).
        max_future_s: latest accepted capture time, seconds after ``now`` (``math.inf``: any).
        max_bytes: largest accepted payload, bytes.
    """

    known_cameras: frozenset[str] | None = None
    bits: int = 16
    max_age_s: float = DEFAULT_MAX_AGE_S
    max_future_s: float = DEFAULT_MAX_FUTURE_S
    max_bytes: int = DEFAULT_MAX_BYTES

    def __post_init__(self) -> None:
        if self.known_cameras is not None:
            object.__setattr__(self, "known_cameras", frozenset(self.known_cameras))
        if self.bits not in (8, 16):
            raise CblrsError(f"bits per channel must be 8 or 16, got {self.bits}.")
        if self.max_age_s < 0 or self.max_future_s < 0 or self.max_bytes <= 0:
            raise CblrsError("max_age_s, max_future_s must be >= 0 and max_bytes > 0.")

    def decode(
        self, payload: bytes, topic_camera: str | None = None, now: float | None = None
    ) -> CameraMessage:
        """:func:`decode_message` with this policy."""
        return self.decode_with_plane(payload, topic_camera, now)[0]

    def decode_wire(
        self,
        payload: bytes,
        topic_camera: str | None = None,
        now: float | None = None,
        topic_plane: int | None = None,
    ) -> WireMessage:
        """:func:`decode_wire` with this policy."""
        return decode_wire(
            payload,
            topic_camera=topic_camera,
            topic_plane=topic_plane,
            known_cameras=self.known_cameras,
            bits=self.bits,
            now=now,
            max_age_s=self.max_age_s,
            max_future_s=self.max_future_s,
            max_bytes=self.max_bytes,
        )

    def decode_with_plane(
        self,
        payload: bytes,
        topic_camera: str | None = None,
        now: float | None = None,
        topic_plane: int | None = None,
    ) -> tuple[CameraMessage, int]:
        """:func:`decode_message_with_plane` with this policy."""
        return decode_message_with_plane(
            payload,
            topic_camera=topic_camera,
            topic_plane=topic_plane,
            known_cameras=self.known_cameras,
            bits=self.bits,
            now=now,
            max_age_s=self.max_age_s,
            max_future_s=self.max_future_s,
            max_bytes=self.max_bytes,
        )


# --------------------------------------------------------------------------- detections


def encode_message(message: CameraMessage, plane_id: int) -> bytes:
    """Serialise a camera message for ``cblrs/<plane>/<camera>/detections``.

    Args:
        message: the frame's message (boxes, confidences, class ids, colours).
        plane_id: the plane the message is for (1..65535).

    Returns:
        UTF-8 JSON bytes, schema ``cblrs.detections/1``.

    Raises:
        RejectedMessage: the message would be refused by a receiver (NaN, unknown class,
            negative box size, colour outside 0..65535, bad camera id, too many detections).

    Example:
        >>> payload = encode_message(CameraMessage.empty("CVLab1", 0, 1.5, 0), plane_id=1)
        >>> decode_message(payload, now=1.5).camera_id
        'CVLab1'
    """
    count = len(message)
    if count > MAX_DETECTIONS:
        raise RejectedMessage(
            RejectReason.OVERSIZED, f"{count} detections, at most {MAX_DETECTIONS} per message"
        )
    class_id = message.class_id
    if count and (class_id.min() < 0 or class_id.max() >= len(CLASS_NAMES)):
        raise RejectedMessage(
            RejectReason.INVALID_VALUE, f"class ids must be 0..{len(CLASS_NAMES) - 1}"
        )
    _check_columns(message.xyxy, message.confidence, message.colour, 16)
    _check_header(message.camera_id, message.sequence, message.timestamp, message.frame, plane_id)
    document = {
        "schema": DETECTIONS_SCHEMA,
        "camera": message.camera_id,
        "sequence": int(message.sequence),
        "timestamp": float(message.timestamp),
        "frame": int(message.frame),
        "plane": int(plane_id),
        "detections": [
            {"class": CLASS_NAMES[klass], "confidence": confidence, "box": box, "colour": colour}
            for klass, confidence, box, colour in zip(
                class_id.tolist(),
                message.confidence.tolist(),
                message.xyxy.tolist(),
                message.colour.tolist(),
                strict=True,
            )
        ],
    }
    return msgspec.json.encode(document)


def decode_message(
    payload: bytes,
    *,
    topic_camera: str | None = None,
    known_cameras: set[str] | frozenset[str] | None = None,
    bits: int = 16,
    now: float | None = None,
    max_age_s: float = DEFAULT_MAX_AGE_S,
    max_future_s: float = DEFAULT_MAX_FUTURE_S,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> CameraMessage:
    """Decode and validate a ``cblrs.detections/1`` payload.

    Args:
        payload: the received bytes.
        topic_camera: camera id taken from the topic; the payload must name the same camera.
        known_cameras: camera ids allowed to send; None accepts any valid id.
        bits: bits per colour channel; colours must lie in 0 .. 2**bits - 1.
        now: current time, seconds since the Unix epoch (default ``time.time()``).
        max_age_s: reject capture times more than this before ``now``.
        max_future_s: reject capture times more than this after ``now``.
        max_bytes: reject larger payloads before parsing them.

    Returns:
        The message (``colour`` as (N, 3) int64, ``xyxy`` (N, 4) float64 pixels).

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    return decode_message_with_plane(
        payload,
        topic_camera=topic_camera,
        known_cameras=known_cameras,
        bits=bits,
        now=now,
        max_age_s=max_age_s,
        max_future_s=max_future_s,
        max_bytes=max_bytes,
    )[0]


def decode_message_with_plane(
    payload: bytes,
    *,
    topic_camera: str | None = None,
    topic_plane: int | None = None,
    known_cameras: set[str] | frozenset[str] | None = None,
    bits: int = 16,
    now: float | None = None,
    max_age_s: float = DEFAULT_MAX_AGE_S,
    max_future_s: float = DEFAULT_MAX_FUTURE_S,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> tuple[CameraMessage, int]:
    """:func:`decode_message` that also returns the payload's plane id.

    ``topic_plane``, when given, must equal the payload's plane (else TOPIC_MISMATCH).
    """
    wire = decode_wire(
        payload,
        topic_camera=topic_camera,
        topic_plane=topic_plane,
        known_cameras=known_cameras,
        bits=bits,
        now=now,
        max_age_s=max_age_s,
        max_future_s=max_future_s,
        max_bytes=max_bytes,
    )
    xyxy, confidence, class_id, colour = _columns(wire.detections, bits)
    message = CameraMessage(
        camera_id=wire.camera,
        sequence=wire.sequence,
        timestamp=wire.timestamp,
        frame=wire.frame,
        xyxy=xyxy,
        confidence=confidence,
        class_id=class_id,
        colour=colour,
    )
    return message, wire.plane


def decode_wire(
    payload: bytes,
    *,
    topic_camera: str | None = None,
    topic_plane: int | None = None,
    known_cameras: set[str] | frozenset[str] | None = None,
    bits: int = 16,
    now: float | None = None,
    max_age_s: float = DEFAULT_MAX_AGE_S,
    max_future_s: float = DEFAULT_MAX_FUTURE_S,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> WireMessage:
    """Decode and validate a ``cblrs.detections/1`` payload into its wire struct.

    The same checks as :func:`decode_message_with_plane` (same arguments), without building
    numpy columns: what a receiver needs to store a message and acknowledge it.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise RejectedMessage(RejectReason.MALFORMED_JSON, "payload is not bytes")
    if len(payload) > max_bytes:
        raise RejectedMessage(
            RejectReason.OVERSIZED, f"payload of {len(payload)} bytes exceeds {max_bytes}"
        )
    wire = _decode_typed(payload, WireMessage, DETECTIONS_SCHEMA)
    if known_cameras is not None and wire.camera not in known_cameras:
        raise RejectedMessage(RejectReason.UNKNOWN_CAMERA, f"camera {wire.camera!r} is not known")
    if topic_camera is not None and wire.camera != topic_camera:
        raise RejectedMessage(
            RejectReason.TOPIC_MISMATCH,
            f"payload camera {wire.camera!r} differs from topic camera {topic_camera!r}",
        )
    if topic_plane is not None and wire.plane != topic_plane:
        raise RejectedMessage(
            RejectReason.TOPIC_MISMATCH,
            f"payload plane {wire.plane} differs from topic plane {topic_plane}",
        )
    if not math.isfinite(wire.timestamp):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "timestamp is not finite")
    current = time.time() if now is None else now
    if current - wire.timestamp > max_age_s:
        raise RejectedMessage(
            RejectReason.TOO_OLD,
            f"captured {current - wire.timestamp:.3f} s ago, more than {max_age_s} s",
        )
    if wire.timestamp - current > max_future_s:
        raise RejectedMessage(
            RejectReason.IN_FUTURE,
            f"captured {wire.timestamp - current:.3f} s in the future, more than {max_future_s} s",
        )
    _check_values(wire.detections, bits)
    return wire


def _check_values(detections: list[WireDetection], bits: int) -> None:
    """Raise :class:`RejectedMessage` unless every detection's values are valid.

    One chained comparison per detection (NaN and infinities fail it too), which for the
    usual handful of detections costs less than building arrays; a failure is then named
    by :func:`_columns`, so the reasons are the same as there.
    """
    top = (1 << bits) - 1
    for item in detections:
        x_min, y_min, x_max, y_max = item.box
        red, green, blue = item.colour
        if not (
            _FLOAT_MIN <= x_min <= x_max <= _FLOAT_MAX
            and _FLOAT_MIN <= y_min <= y_max <= _FLOAT_MAX
            and 0.0 <= item.confidence <= 1.0
            and 0 <= red <= top
            and 0 <= green <= top
            and 0 <= blue <= top
            and item.class_name in CLASS_IDS
        ):
            _columns(detections, bits)  # raises, naming the fault
            raise AssertionError("unreachable")  # _columns refuses what failed above


_FLOAT_MAX = float(np.finfo(np.float64).max)
_FLOAT_MIN = -_FLOAT_MAX


def _check_header(camera_id: str, sequence: int, timestamp: float, frame: int, plane: int) -> None:
    try:
        msgspec.convert(
            {"camera": camera_id, "sequence": int(sequence), "frame": int(frame), "plane": plane},
            _Header,
        )
    except (msgspec.ValidationError, TypeError, ValueError) as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    if not math.isfinite(float(timestamp)):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "timestamp is not finite")


class _Header(msgspec.Struct, forbid_unknown_fields=True):
    camera: CameraId
    sequence: Count
    frame: Count
    plane: PlaneId


def _columns(
    detections: list[WireDetection], bits: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Decoded detections as validated columns, built and checked all at once.

    Returns:
        ``xyxy`` (N, 4) float64 pixels, ``confidence`` (N,) float64, ``class_id`` (N,) int64
        and ``colour`` (N, 3) int64.

    Raises:
        RejectedMessage: unknown class, non-finite or inverted box, confidence outside 0..1,
            colour outside ``0 .. 2**bits - 1``.
    """
    if not detections:
        return _EMPTY_XYXY, _EMPTY_FLOAT, _EMPTY_INT, _EMPTY_COLOUR
    try:
        class_id = np.fromiter(
            [CLASS_IDS[item.class_name] for item in detections], np.int64, len(detections)
        )
    except KeyError as error:
        raise RejectedMessage(
            RejectReason.INVALID_VALUE,
            f"unknown class {error.args[0]!r}; known: {', '.join(CLASS_NAMES)}",
        ) from None
    # One table, one conversion, one bounds test for every value (NaN and infinities fail
    # it too), whatever the number of detections; the detailed checks only name the fault.
    table = np.array(
        [(*item.box, item.confidence, *item.colour) for item in detections], np.float64
    )
    if not (
        ((_LOWER <= table) & (table <= _UPPER[bits])).all()
        and (table[:, 2:4] >= table[:, 0:2]).all()
    ):
        try:
            colour = np.array([item.colour for item in detections], np.int64)
        except OverflowError:
            raise RejectedMessage(
                RejectReason.COLOUR_OUT_OF_RANGE, f"colour outside 0..{(1 << bits) - 1}"
            ) from None
        _check_columns(table[:, :4], table[:, 4], colour, bits)
        raise RejectedMessage(RejectReason.INVALID_VALUE, "detection values out of range")
    return table[:, :4], table[:, 4], class_id, table[:, 5:].astype(np.int64)


_LOWER = np.array([-np.finfo(np.float64).max] * 4 + [0.0] * 4)
"""Lowest allowed value per column of the (box, confidence, colour) table."""
_UPPER = {
    bits: np.array([np.finfo(np.float64).max] * 4 + [1.0] + [float((1 << bits) - 1)] * 3)
    for bits in (8, 16)
}
"""Highest allowed value per column, by bits per colour channel."""
_EMPTY_XYXY = np.zeros((0, 4))
_EMPTY_FLOAT = np.zeros(0)
_EMPTY_INT = np.zeros(0, np.int64)
_EMPTY_COLOUR = np.zeros((0, 3), np.int64)
for _empty in (_EMPTY_XYXY, _EMPTY_FLOAT, _EMPTY_INT, _EMPTY_COLOUR):
    _empty.setflags(write=False)


def _check_columns(
    xyxy: np.ndarray, confidence: np.ndarray, colour: np.ndarray, bits: int
) -> None:
    """Value checks shared by the sender and the receiver."""
    if not np.isfinite(xyxy).all():
        raise RejectedMessage(RejectReason.INVALID_VALUE, "box coordinates must be finite")
    if (xyxy[:, 2] < xyxy[:, 0]).any() or (xyxy[:, 3] < xyxy[:, 1]).any():
        raise RejectedMessage(
            RejectReason.INVALID_VALUE, "boxes must have x_max >= x_min and y_max >= y_min"
        )
    if not np.isfinite(confidence).all() or ((confidence < 0) | (confidence > 1)).any():
        raise RejectedMessage(RejectReason.INVALID_VALUE, "confidences must lie in 0..1")
    maximum = (1 << bits) - 1
    if ((colour < 0) | (colour > maximum)).any():
        raise RejectedMessage(
            RejectReason.COLOUR_OUT_OF_RANGE, f"colour outside 0..{maximum} ({bits}-bit channels)"
        )


def _decode_typed(payload: bytes, struct_type: type[_T], schema: str) -> _T:
    """Decode JSON into ``struct_type`` and check its schema tag, or raise RejectedMessage."""
    try:
        decoded = msgspec.json.decode(payload, type=struct_type)
    except (msgspec.DecodeError, msgspec.ValidationError, RecursionError, ValueError):
        _classify_failure(payload, schema, struct_type)
        raise AssertionError("unreachable") from None  # _classify_failure always raises
    found = decoded.schema  # type: ignore[attr-defined]
    if found != schema:
        raise RejectedMessage(
            RejectReason.WRONG_SCHEMA, f"schema {found!r}, expected {schema!r}"
        )
    return decoded


def _classify_failure(payload: bytes, schema: str, struct_type: type) -> None:
    """Turn a failed typed decode into the most specific :class:`RejectedMessage`."""
    try:
        document = msgspec.json.decode(payload)
    except msgspec.ValidationError as error:  # e.g. numbers out of the double range
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    except (msgspec.DecodeError, RecursionError, ValueError) as error:
        if _parses_with_constants(payload):
            raise RejectedMessage(
                RejectReason.INVALID_VALUE, "NaN and Infinity are not valid JSON numbers"
            ) from None
        raise RejectedMessage(RejectReason.MALFORMED_JSON, str(error)) from None
    if not isinstance(document, dict):
        raise RejectedMessage(
            RejectReason.MALFORMED_JSON, f"top level is {type(document).__name__}, not an object"
        )
    if "schema" not in document:
        raise RejectedMessage(RejectReason.MISSING_FIELD, "object missing required field `schema`")
    if document["schema"] != schema:
        raise RejectedMessage(
            RejectReason.WRONG_SCHEMA, f"schema {document['schema']!r}, expected {schema!r}"
        )
    try:
        msgspec.convert(document, struct_type)
    except msgspec.ValidationError as error:
        text = str(error)
        if "missing required field" in text:
            raise RejectedMessage(RejectReason.MISSING_FIELD, text) from None
        if "unknown field" in text:
            raise RejectedMessage(RejectReason.UNKNOWN_FIELD, text) from None
        raise RejectedMessage(RejectReason.INVALID_VALUE, text) from None
    except (RecursionError, ValueError, TypeError) as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    # The generic path accepted what the typed path refused; refuse it all the same.
    raise RejectedMessage(RejectReason.INVALID_VALUE, "payload does not match the schema")


def _parses_with_constants(payload: bytes) -> bool:
    """Whether the payload is JSON apart from NaN/Infinity literals (what Python emits)."""
    seen: list[str] = []

    def constant(name: str) -> float:
        seen.append(name)
        return math.nan

    try:
        json.loads(bytes(payload), parse_constant=constant)
    except (ValueError, RecursionError, UnicodeDecodeError):
        return False
    return bool(seen)


# --------------------------------------------------------------------------- tracks


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


class WireTracks(msgspec.Struct, forbid_unknown_fields=True):
    """A ``cblrs.tracks/1`` payload."""

    schema: str
    plane: PlaneId
    sequence: Count
    tracks: Annotated[list[WireTrack], msgspec.Meta(max_length=MAX_TRACK_ROWS)]
    cameras: Annotated[list[CameraId], msgspec.Meta(max_length=1000)] = msgspec.field(
        default_factory=list
    )
    timestamp: float | None = None


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
    """

    plane_id: int
    sequence: int
    tracks: Tracks
    cameras: tuple[str, ...] = field(default=())
    timestamp: float | None = None


def encode_tracks(
    tracks: Tracks,
    plane_id: int,
    *,
    sequence: int = 0,
    cameras: list[str] | None = None,
    timestamp: float | None = None,
) -> bytes:
    """Serialise track rows for ``cblrs/<plane>/tracks`` (schema ``cblrs.tracks/1``).

    Args:
        tracks: rows to publish; NaN boxes are sent as ``null``.
        plane_id: the plane.
        sequence: the matcher's update counter.
        cameras: camera ids that ``tracks.camera_id`` indexes (optional).
        timestamp: the update's time (the released group's capture time; optional).

    Raises:
        RejectedMessage: non-finite positions or times, or too many rows.
    """
    if len(tracks) > MAX_TRACK_ROWS:
        raise RejectedMessage(
            RejectReason.OVERSIZED, f"{len(tracks)} rows, at most {MAX_TRACK_ROWS} per update"
        )
    if not (np.isfinite(tracks.world_xy).all() and np.isfinite(tracks.timestamp).all()):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "track positions must be finite")
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
    return TracksUpdate(wire.plane, wire.sequence, tracks, tuple(wire.cameras), wire.timestamp)


# --------------------------------------------------------------------------- status

StatusState = Literal["online", "offline"]


class Status(msgspec.Struct, forbid_unknown_fields=True, frozen=True, omit_defaults=True):
    """A ``cblrs.status/1`` payload: availability of a camera or matcher.

    Attributes:
        schema: the schema tag.
        client: the camera or matcher id.
        role: "camera", "matcher" or "viewer".
        state: "online" or "offline".
        timestamp: when it was published (seconds since the epoch); None in a last will,
            which is composed at connection time.
        session_present: a matcher's "online": whether the broker still held its session
            (False: nothing was queued for it, so cameras send again what it has not
            confirmed); None when not said.
    """

    schema: str
    client: CameraId
    role: Literal["camera", "matcher", "viewer"]
    state: StatusState
    timestamp: float | None = None
    session_present: bool | None = None


def encode_status(
    client: str,
    state: StatusState,
    *,
    role: str = "camera",
    timestamp: float | None = None,
    session_present: bool | None = None,
) -> bytes:
    """Serialise an availability payload (publish retained on the status topic)."""
    document: dict[str, Any] = {
        "schema": STATUS_SCHEMA,
        "client": client,
        "role": role,
        "state": state,
        "timestamp": timestamp,
    }
    if session_present is not None:
        document["session_present"] = session_present
    try:
        status = msgspec.convert(document, Status)
    except msgspec.ValidationError as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    return msgspec.json.encode(status)


def decode_status(payload: bytes) -> Status:
    """Decode an availability payload.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if len(payload) > 4096:
        raise RejectedMessage(RejectReason.OVERSIZED, f"status of {len(payload)} bytes")
    return _decode_typed(payload, Status, STATUS_SCHEMA)
