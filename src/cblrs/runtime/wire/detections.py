"""``cblrs.detections/1``: a camera's frame on ``cblrs/<plane>/<camera>/detections``.

:func:`encode_message` on the camera; on the receiver :class:`ValidationPolicy` holds what is
accepted (known cameras, bits, age and size limits) and decodes: :meth:`ValidationPolicy.decode`,
:meth:`ValidationPolicy.decode_with_plane`, :meth:`ValidationPolicy.decode_wire`. The functions
:func:`decode_message`, :func:`decode_message_with_plane` and :func:`decode_wire` take the same
limits as keywords and build the policy once.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Annotated

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage
from cblrs.errors import CblrsError
from cblrs.runtime.wire.common import (
    _FLOAT_MAX,
    _FLOAT_MIN,
    CLASS_IDS,
    DEFAULT_MAX_AGE_S,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_FUTURE_S,
    DETECTIONS_SCHEMA,
    MAX_DETECTIONS,
    CameraId,
    ClassName,
    Count,
    PlaneId,
    RejectedMessage,
    RejectReason,
    _decode_typed,
)


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
        """Decode and validate a ``cblrs.detections/1`` payload into its wire struct.

        Every check of :meth:`decode_with_plane`, without building numpy columns: what a
        receiver needs to store a message and acknowledge it.

        Args:
            payload: the received bytes.
            topic_camera: camera id taken from the topic; the payload must name the same camera.
            now: current time, seconds since the Unix epoch (default ``time.time()``).
            topic_plane: plane id taken from the topic; the payload must name the same plane.

        Raises:
            RejectedMessage: for every kind of bad input, and nothing else.
        """
        if not isinstance(payload, bytes | bytearray | memoryview):
            raise RejectedMessage(RejectReason.MALFORMED_JSON, "payload is not bytes")
        if len(payload) > self.max_bytes:
            raise RejectedMessage(
                RejectReason.OVERSIZED, f"payload of {len(payload)} bytes exceeds {self.max_bytes}"
            )
        wire = _decode_typed(payload, WireMessage, DETECTIONS_SCHEMA)
        if self.known_cameras is not None and wire.camera not in self.known_cameras:
            raise RejectedMessage(
                RejectReason.UNKNOWN_CAMERA, f"camera {wire.camera!r} is not known"
            )
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
        if current - wire.timestamp > self.max_age_s:
            raise RejectedMessage(
                RejectReason.TOO_OLD,
                f"captured {current - wire.timestamp:.3f} s ago, more than {self.max_age_s} s",
            )
        if wire.timestamp - current > self.max_future_s:
            raise RejectedMessage(
                RejectReason.IN_FUTURE,
                f"captured {wire.timestamp - current:.3f} s in the future, "
                f"more than {self.max_future_s} s",
            )
        _check_values(wire.detections, self.bits)
        return wire

    def decode_with_plane(
        self,
        payload: bytes,
        topic_camera: str | None = None,
        now: float | None = None,
        topic_plane: int | None = None,
    ) -> tuple[CameraMessage, int]:
        """:meth:`decode` that also returns the payload's plane id."""
        wire = self.decode_wire(payload, topic_camera, now, topic_plane)
        xyxy, confidence, class_id, colour = _columns(wire.detections, self.bits)
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
    return ValidationPolicy(
        known_cameras=None if known_cameras is None else frozenset(known_cameras),
        bits=bits, max_age_s=max_age_s,
        max_future_s=max_future_s, max_bytes=max_bytes,
    ).decode(payload, topic_camera, now)


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
    return ValidationPolicy(
        known_cameras=None if known_cameras is None else frozenset(known_cameras),
        bits=bits, max_age_s=max_age_s,
        max_future_s=max_future_s, max_bytes=max_bytes,
    ).decode_with_plane(
        payload, topic_camera, now, topic_plane
    )


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
    return ValidationPolicy(
        known_cameras=None if known_cameras is None else frozenset(known_cameras),
        bits=bits, max_age_s=max_age_s,
        max_future_s=max_future_s, max_bytes=max_bytes,
    ).decode_wire(
        payload, topic_camera, now, topic_plane
    )


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


_UPPER = {
    bits: np.array([np.finfo(np.float64).max] * 4 + [1.0] + [float((1 << bits) - 1)] * 3)
    for bits in (8, 16)
}


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
