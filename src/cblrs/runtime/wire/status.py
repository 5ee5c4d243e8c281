"""``cblrs.status/1``: retained availability ("online"/"offline") on the status topics.
"""

from __future__ import annotations

from typing import Any, Literal

import msgspec

from cblrs.runtime.wire.common import (
    STATUS_SCHEMA,
    CameraId,
    RejectedMessage,
    RejectReason,
    _decode_typed,
)

StatusState = Literal["online", "offline"]


class Status(msgspec.Struct, forbid_unknown_fields=True, frozen=True, omit_defaults=True):
    """A ``cblrs.status/1`` payload: availability of a camera or matcher.

    Attributes:
        schema: the schema tag.
        client: the camera or matcher id.
        role: "camera", "matcher", "linker" or "viewer".
        state: "online" or "offline".
        timestamp: when it was published (seconds since the epoch); None in a last will,
            which is composed at connection time.
        session_present: a matcher's "online": whether the broker still held its session
            (False: nothing was queued for it, so cameras send again what it has not
            confirmed); None when not said.
    """

    schema: str
    client: CameraId
    role: Literal["camera", "matcher", "linker", "viewer"]
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
