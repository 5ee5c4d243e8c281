"""Shared parts of the wire formats: schema tags, limits, bounded field types, and the
rejection every decoder raises (:class:`RejectedMessage` with a :class:`RejectReason`).
"""

from __future__ import annotations

import json
import math
from enum import Enum
from typing import Annotated, TypeVar

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.errors import CblrsError
from cblrs.runtime.transport.topics import ID_PATTERN, MAX_ID_LENGTH, MAX_PLANE_ID

_T = TypeVar("_T")


DETECTIONS_SCHEMA = "cblrs.detections/1"


TRACKS_SCHEMA = "cblrs.tracks/1"


STATUS_SCHEMA = "cblrs.status/1"


MAX_DETECTIONS = 1000


MAX_TRACK_ROWS = 10000


DEFAULT_MAX_BYTES = 256 * 1024


DEFAULT_MAX_AGE_S = 24 * 3600.0


DEFAULT_MAX_FUTURE_S = 60.0


MAX_INT = 2**53


CLASS_IDS = {name: index for index, name in enumerate(CLASS_NAMES)}


CameraId = Annotated[
    str, msgspec.Meta(min_length=1, max_length=MAX_ID_LENGTH, pattern=ID_PATTERN)
]


Count = Annotated[int, msgspec.Meta(ge=0, le=MAX_INT)]


PlaneId = Annotated[int, msgspec.Meta(ge=1, le=MAX_PLANE_ID)]


SITE_PLANE = 0
"""The plane id of what covers the whole site (the linker's global tracks, the site's
analytics): 0, the B channel's "no plane", which no real plane has."""


SitePlaneId = Annotated[int, msgspec.Meta(ge=0, le=MAX_PLANE_ID)]
"""A plane id, or :data:`SITE_PLANE` for the whole site."""


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


_FLOAT_MAX = float(np.finfo(np.float64).max)


_FLOAT_MIN = -_FLOAT_MAX


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
