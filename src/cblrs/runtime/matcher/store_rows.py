"""How the matcher database holds camera messages and tracks: the inbox entry of a message
(its header columns and its detections as compact JSON) and the ``tracks`` table's rows, both
ways.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import msgspec
import numpy as np

from cblrs.detections import MESSAGE_SCHEMA, CameraMessage, Tracks
from cblrs.runtime.wire import CLASS_IDS, WireMessage


@dataclass(frozen=True)
class StoredMessage:
    """An inbox row with its decoded message."""

    message: CameraMessage
    status: str
    received_at: float


class InboxEntry(NamedTuple):
    """An accepted message as the inbox holds it: its header and its detections as JSON.

    What the receiver stores, orders and hands to the tracker: cheap to build from the
    decoded wire struct and to send to another process; :meth:`message` builds the numpy
    columns when they are needed.
    """

    camera_id: str
    sequence: int
    timestamp: float
    frame: int
    body: str
    """The detection columns as compact JSON (see :func:`message_body`)."""

    @classmethod
    def from_wire(cls, wire: WireMessage) -> InboxEntry:
        """The entry of a validated ``cblrs.detections/1`` payload."""
        detections = wire.detections
        body = _encoder.encode(
            {
                "xyxy": [item.box for item in detections],
                "confidence": [item.confidence for item in detections],
                "class_id": [CLASS_IDS[item.class_name] for item in detections],
                "colour": [item.colour for item in detections],
            }
        )
        return cls(wire.camera, wire.sequence, wire.timestamp, wire.frame, body.decode())

    @classmethod
    def from_message(cls, message: CameraMessage) -> InboxEntry:
        """The entry of a camera message.

        Raises:
            ValueError: a value is NaN or infinite (JSON has no such numbers).
        """
        return cls(
            message.camera_id,
            int(message.sequence),
            float(message.timestamp),
            int(message.frame),
            message_body(message),
        )

    def message(self) -> CameraMessage:
        """The camera message, with its numpy columns."""
        return message_from_row(self.camera_id, self.sequence, self.timestamp, self.frame,
                                self.body)


def message_body(message: CameraMessage) -> str:
    """The detection columns of a message as compact JSON (the inbox ``body``).

    Raises:
        ValueError: a value is NaN or infinite (JSON has no such numbers).
    """
    body = _encoder.encode(
        {
            "xyxy": message.xyxy.tolist(),
            "confidence": message.confidence.tolist(),
            "class_id": message.class_id.tolist(),
            "colour": message.colour.tolist(),
        }
    )
    if b"null" in body:  # msgspec writes NaN and infinities as null
        raise ValueError("Out of range float values are not JSON compliant")
    return body.decode()


_encoder = msgspec.json.Encoder()

_decoder = msgspec.json.Decoder()


def message_from_row(camera_id: str, sequence: int, timestamp: float, frame: int, body: str):
    """A :class:`CameraMessage` rebuilt from an inbox row (its columns and JSON body).

    The body was written by :func:`message_body` or :meth:`InboxEntry.from_wire` from a
    message already checked, so the columns are set without ``CameraMessage``'s checks again
    (a third of this function's cost with small messages, which the tracker process pays for
    every message); only their shapes and lengths are checked, as those checks would.
    """
    data = _decoder.decode(body)
    xyxy = np.array(data["xyxy"], dtype=np.float64)
    confidence = np.array(data["confidence"], dtype=np.float64)
    class_id = np.array(data["class_id"], dtype=np.int64)
    colour = np.array(data["colour"], dtype=np.int64)
    count = len(confidence)
    if not len(xyxy) == len(class_id) == len(colour) == count or confidence.ndim != 1 \
            or class_id.ndim != 1 or (count and (xyxy.shape[1:] != (4,)
                                                 or colour.shape[1:] != (3,))):
        raise ValueError(f"inbox row {camera_id}/{sequence} holds columns of other shapes")
    message = _new(CameraMessage)
    _set(message, "camera_id", camera_id)
    _set(message, "sequence", int(sequence))
    _set(message, "timestamp", float(timestamp))
    _set(message, "frame", int(frame))
    _set(message, "xyxy", xyxy.reshape(-1, 4))
    _set(message, "confidence", confidence)
    _set(message, "class_id", class_id)
    _set(message, "colour", colour.reshape(-1, 3))
    _set(message, "schema", MESSAGE_SCHEMA)
    return message


_new = object.__new__
_set = object.__setattr__


INSERT_TRACKS = (
    "INSERT INTO tracks (frame, timestamp, track_id, x, y, camera, "
    "x_min, y_min, x_max, y_max, class_id) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
)
"""Insert one row of :func:`track_rows` into the ``tracks`` table."""


def track_rows(tracks: Tracks) -> list[tuple]:
    """The ``tracks`` table rows of :class:`Tracks` (NaN boxes and class -1 as NULL)."""
    if not len(tracks):
        return []
    # Whole columns to Python numbers at once (``tolist`` gives the same ints and floats as
    # converting element by element, several times faster with WILDTRACK-sized groups).
    boxes = np.asarray(tracks.xyxy, dtype=np.float64)
    box_values: list[list[float | None]] = boxes.tolist()
    if not np.isfinite(boxes).all():
        box_values = [[value if math.isfinite(value) else None for value in row]
                      for row in box_values]
    classes = [None if value < 0 else value for value in tracks.class_id.tolist()]
    world = tracks.world_xy.tolist()
    return [
        (frame, timestamp, track_id, x_y[0], x_y[1], camera, *box, class_id)
        for frame, timestamp, track_id, x_y, camera, box, class_id in zip(
            tracks.frame.tolist(), tracks.timestamp.tolist(), tracks.track_id.tolist(), world,
            tracks.camera_id.tolist(), box_values, classes, strict=True)
    ]


def tracks_from_rows(rows: Sequence[Sequence[Any]]) -> Tracks:
    """Track rows ``(frame, timestamp, track_id, x, y, camera, x_min, y_min, x_max, y_max,
    class_id)`` as :class:`Tracks` (NULL boxes become NaN, a NULL class -1)."""
    if not rows:
        return Tracks.empty()
    table = np.array(rows, dtype=object)
    return Tracks(
        frame=table[:, 0].astype(np.int64),
        timestamp=table[:, 1].astype(np.float64),
        track_id=table[:, 2].astype(np.int64),
        world_xy=table[:, 3:5].astype(np.float64),
        camera_id=table[:, 5].astype(np.int64),
        xyxy=np.where(table[:, 6:10] == None, np.nan, table[:, 6:10]).astype(np.float64),  # noqa: E711
        class_id=np.where(table[:, 10] == None, -1, table[:, 10]).astype(np.int64),  # noqa: E711
    )
