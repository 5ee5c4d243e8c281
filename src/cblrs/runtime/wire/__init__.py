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

The formats live one per module: :mod:`~cblrs.runtime.wire.detections`,
:mod:`~cblrs.runtime.wire.tracks`, :mod:`~cblrs.runtime.wire.status`, with their shared parts
in :mod:`~cblrs.runtime.wire.common`; every public name is importable from here.
"""

from __future__ import annotations

from cblrs.runtime.wire.common import (
    CLASS_IDS,
    DEFAULT_MAX_AGE_S,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_FUTURE_S,
    DETECTIONS_SCHEMA,
    MAX_DETECTIONS,
    MAX_INT,
    MAX_TRACK_ROWS,
    SITE_PLANE,
    STATUS_SCHEMA,
    TRACKS_SCHEMA,
    CameraId,
    ClassName,
    Count,
    PlaneId,
    RejectedMessage,
    RejectReason,
    SitePlaneId,
)
from cblrs.runtime.wire.detections import (
    ValidationPolicy,
    WireDetection,
    WireMessage,
    decode_message,
    decode_message_with_plane,
    decode_wire,
    encode_message,
)
from cblrs.runtime.wire.status import (
    Status,
    StatusState,
    decode_status,
    encode_status,
)
from cblrs.runtime.wire.tracks import (
    TracksUpdate,
    WireTrack,
    WireTracks,
    decode_tracks,
    encode_tracks,
)

__all__ = [
    "CLASS_IDS",
    "DEFAULT_MAX_AGE_S",
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_FUTURE_S",
    "DETECTIONS_SCHEMA",
    "MAX_DETECTIONS",
    "MAX_INT",
    "MAX_TRACK_ROWS",
    "SITE_PLANE",
    "STATUS_SCHEMA",
    "TRACKS_SCHEMA",
    "CameraId",
    "ClassName",
    "Count",
    "PlaneId",
    "RejectReason",
    "RejectedMessage",
    "SitePlaneId",
    "Status",
    "StatusState",
    "TracksUpdate",
    "ValidationPolicy",
    "WireDetection",
    "WireMessage",
    "WireTrack",
    "WireTracks",
    "decode_message",
    "decode_message_with_plane",
    "decode_status",
    "decode_tracks",
    "decode_wire",
    "encode_message",
    "encode_status",
    "encode_tracks",
]
