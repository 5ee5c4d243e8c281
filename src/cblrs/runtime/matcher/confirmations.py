"""End-to-end confirmations: the matcher tells each camera which messages it has stored.

A broker's acknowledgement (PUBACK) only says the broker took a message; Mosquitto may still
drop it later (a full queue, no subscriber yet, a crash between two saves of its database).
So a camera keeps every message in its spool (:mod:`cblrs.runtime.camera.spool`) until the matcher
confirms it, on ``cblrs/<plane>/<camera>/stored``, after the message is committed to the
matcher's SQLite inbox (or was a duplicate of one that is, or was rejected by validation)::

    {"schema": "cblrs.stored/1", "camera": "CVLab1", "matcher": "matcher1",
     "stored": [[0, 49], [51, 60]], "rejected": {"too_old": [[50, 50]]}}

Ranges are inclusive sequence numbers. A camera that misses a confirmation (it was
disconnected) sends the message again later; the matcher recognises it by ``(camera,
sequence)`` and confirms it again.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Iterable
from typing import Annotated

import msgspec

from cblrs.runtime.transport.topics import MAX_ID_LENGTH, TopicError, stored_topic
from cblrs.runtime.wire import CameraId, RejectedMessage, RejectReason

STORED_SCHEMA = "cblrs.stored/1"
MAX_RANGES = 10_000
MAX_SEQUENCE = 2**63 - 1

Sequence = Annotated[int, msgspec.Meta(ge=0, le=MAX_SEQUENCE)]
Range = tuple[Sequence, Sequence]


class StoredConfirmation(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """A ``cblrs.stored/1`` payload (see the module docstring)."""

    schema: str
    camera: CameraId
    matcher: Annotated[str, msgspec.Meta(max_length=MAX_ID_LENGTH)]
    stored: Annotated[list[Range], msgspec.Meta(max_length=MAX_RANGES)] = msgspec.field(
        default_factory=list
    )
    rejected: dict[str, Annotated[list[Range], msgspec.Meta(max_length=MAX_RANGES)]] = (
        msgspec.field(default_factory=dict)
    )

    def stored_sequences(self) -> list[int]:
        return [value for first, last in self.stored for value in range(first, last + 1)]

    def rejected_sequences(self) -> dict[str, list[int]]:
        return {
            reason: [value for first, last in ranges for value in range(first, last + 1)]
            for reason, ranges in self.rejected.items()
        }


_decoder = msgspec.json.Decoder(StoredConfirmation)


def decode_confirmation(payload: bytes) -> StoredConfirmation:
    """Decode a confirmation.

    Raises:
        RejectedMessage: not a valid ``cblrs.stored/1`` payload.
    """
    try:
        confirmation = _decoder.decode(payload)
    except msgspec.DecodeError as error:
        raise RejectedMessage(RejectReason.MALFORMED_JSON, str(error)) from None
    if confirmation.schema != STORED_SCHEMA:
        raise RejectedMessage(RejectReason.WRONG_SCHEMA, f"schema {confirmation.schema!r}")
    for first, last in [*confirmation.stored,
                        *(item for ranges in confirmation.rejected.values() for item in ranges)]:
        if last < first or last - first > 10_000_000:
            raise RejectedMessage(RejectReason.INVALID_VALUE, f"bad range [{first}, {last}]")
    return confirmation


def to_ranges(sequences: Iterable[int]) -> list[list[int]]:
    """Sorted inclusive ``[first, last]`` ranges covering ``sequences``."""
    ranges: list[list[int]] = []
    for value in sorted(set(sequences)):
        if ranges and value == ranges[-1][1] + 1:
            ranges[-1][1] = value
        else:
            ranges.append([value, value])
    return ranges


class _Header(msgspec.Struct):
    camera: str
    sequence: int


_header_decoder = msgspec.json.Decoder(_Header)


def peek_sequence(payload: bytes, topic_camera: str) -> int | None:
    """The sequence number of a rejected payload, if it names ``topic_camera`` and has one."""
    try:
        header = _header_decoder.decode(payload)
    except (msgspec.DecodeError, ValueError):
        return None
    if header.camera != topic_camera or not 0 <= header.sequence <= MAX_SEQUENCE:
        return None
    return header.sequence


class ConfirmationBuffer:
    """What the matcher stored or rejected since its last confirmations, per camera.

    The receiver adds sequences after each inbox commit; :meth:`take` returns the
    ``(topic, payload)`` confirmations to publish (one per camera) and empties the buffer.
    Thread-safe.

    Args:
        plane_id: the plane served.
        matcher_id: the matcher's id (named in every confirmation).
    """

    def __init__(self, plane_id: int, matcher_id: str):
        self.plane_id = int(plane_id)
        self.matcher_id = matcher_id
        self._stored: dict[str, list[int]] = defaultdict(list)
        self._rejected: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
        self._lock = threading.Lock()

    def add_stored(self, camera_id: str, sequence: int) -> None:
        with self._lock:
            self._stored[camera_id].append(int(sequence))

    def add_rejected(self, camera_id: str, sequence: int, reason: str) -> None:
        with self._lock:
            self._rejected[camera_id][reason].append(int(sequence))

    def __bool__(self) -> bool:
        with self._lock:
            return bool(self._stored or self._rejected)

    def take(self) -> list[tuple[str, bytes]]:
        with self._lock:
            stored, rejected = self._stored, self._rejected
            self._stored = defaultdict(list)
            self._rejected = defaultdict(lambda: defaultdict(list))
        messages = []
        for camera in sorted(set(stored) | set(rejected)):
            try:
                topic = stored_topic(self.plane_id, camera)
            except TopicError:
                continue
            document = {
                "schema": STORED_SCHEMA,
                "camera": camera,
                "matcher": self.matcher_id,
                "stored": to_ranges(stored.get(camera, ())),
                "rejected": {
                    reason: to_ranges(values)
                    for reason, values in sorted(rejected.get(camera, {}).items())
                },
            }
            messages.append((topic, msgspec.json.encode(document)))
        return messages
