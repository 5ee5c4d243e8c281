"""The matcher's analytics on the wire: events (``cblrs.events/1``) and the live summary
(``cblrs.live/1``), JSON validated like the other messages (:mod:`cblrs.runtime.wire`).

* ``cblrs.events/1`` on ``cblrs/<plane>/events``, QoS 1, one message per event::

      {"schema": "cblrs.events/1", "plane": 1, "id": 17, "kind": "line_crossed",
       "timestamp": 1700000012.4, "track": 42, "class": "person", "place": "north_flow",
       "direction": "positive", "world_xy": [3.1, 17.0], "total": 9,
       "key": "line_crossed/north_flow/42/1700000012.4"}

  ``kind`` is ``line_crossed`` (with ``direction`` and ``world_xy``), ``zone_entered``
  (``crossed``: entered across the border, or first seen inside) or ``zone_left``
  (``entered_at``, ``dwell_s``, ``entered``, ``exited``: left across the border, or the
  track was lost inside), or ``event_retracted``: a correction of the past (late messages
  re-tracked, :mod:`cblrs.runtime.matcher.retrack`) no longer finds the published event whose key
  is ``retracted`` (its kind ``retracted_kind``; the live summary's counters are already
  the corrected ones). ``total`` (not in a retraction) is the running count of that
  place's events of the kind (crossings in that direction; visits begun; visits ended), all
  classes. ``id`` is
  the plane's event sequence in the matcher's database, ``key`` the event's natural
  identity: QoS 1 may deliver an event twice (a matcher killed between the broker's
  acknowledgement and marking it published sends it again), so subscribers de-duplicate by
  ``key``. Times are capture times, seconds since the Unix epoch; with a site ``timezone``
  ``time`` gives the same instant as a local ISO time with its offset.
* ``cblrs.live/1`` on ``cblrs/<plane>/live``, QoS 0, retained, about once a second: the
  persistent counters, each zone's occupancy and live dwell (open visits of confirmed
  tracks), and each camera's health as the matcher sees it (online, messages received and
  rejected, message rate, age of its last message).
* ``cblrs.alerts/1`` on ``cblrs/<plane>/alerts``, QoS 1, retained: an alert episode fired or
  cleared, with the episodes firing then (:class:`WireAlert`, :mod:`cblrs.alerts`).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from cblrs.runtime.wire.common import (
    MAX_INT,
    CameraId,
    ClassName,
    Count,
    RejectedMessage,
    RejectReason,
    SitePlaneId,
    _decode_typed,
)

EVENTS_SCHEMA = "cblrs.events/1"
LIVE_SCHEMA = "cblrs.live/1"
EVENT_KINDS = ("line_crossed", "zone_entered", "zone_left", "event_retracted")
MAX_EVENT_BYTES = 4096
MAX_LIVE_BYTES = 1024 * 1024

PlaceName = Annotated[str, msgspec.Meta(min_length=1, max_length=128)]


class WireEvent(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    """A ``cblrs.events/1`` payload (see the module docstring)."""

    schema: str
    plane: SitePlaneId
    id: Count
    kind: Literal["line_crossed", "zone_entered", "zone_left", "event_retracted"]
    timestamp: float
    track: Annotated[int, msgspec.Meta(ge=-MAX_INT, le=MAX_INT)]
    place: PlaceName
    key: Annotated[str, msgspec.Meta(min_length=1, max_length=512)]
    total: Count | None = None
    class_name: ClassName | None = msgspec.field(default=None, name="class")
    direction: Literal["positive", "negative"] | None = None
    world_xy: tuple[float, float] | None = None
    crossed: bool | None = None
    entered_at: float | None = None
    dwell_s: float | None = None
    entered: bool | None = None
    exited: bool | None = None
    # The local ISO time with offset, when the site has a timezone (cblrs.localtime).
    time: Annotated[str, msgspec.Meta(min_length=1, max_length=64)] | None = None
    retracted: Annotated[str, msgspec.Meta(min_length=1, max_length=512)] | None = None
    retracted_kind: Literal["line_crossed", "zone_entered", "zone_left"] | None = None


_REQUIRED = {
    "line_crossed": ("total", "direction", "world_xy"),
    "zone_entered": ("total", "crossed"),
    "zone_left": ("total", "entered_at", "dwell_s", "entered", "exited"),
    "event_retracted": ("retracted", "retracted_kind"),
}


def encode_event(body: dict[str, Any], plane_id: int, event_id: int) -> bytes:
    """The payload of a stored event (``events.body``) with its plane and id.

    Raises:
        RejectedMessage: the event would not pass :func:`decode_event`.
    """
    document = {"schema": EVENTS_SCHEMA, "plane": int(plane_id), "id": int(event_id), **body}
    try:
        event = msgspec.convert(document, WireEvent)
    except msgspec.ValidationError as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    _check_event(event)
    return msgspec.json.encode(event)


def decode_event(payload: bytes) -> WireEvent:
    """Decode and validate a ``cblrs.events/1`` payload.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if len(payload) > MAX_EVENT_BYTES:
        raise RejectedMessage(RejectReason.OVERSIZED, f"event of {len(payload)} bytes")
    event = _decode_typed(payload, WireEvent, EVENTS_SCHEMA)
    _check_event(event)
    return event


def _check_event(event: WireEvent) -> None:
    missing = [name for name in _REQUIRED[event.kind] if getattr(event, name) is None]
    if missing:
        raise RejectedMessage(
            RejectReason.MISSING_FIELD, f"a {event.kind} event needs {', '.join(missing)}"
        )
    others = {name for names in _REQUIRED.values() for name in names} - set(_REQUIRED[event.kind])
    extra = sorted(name for name in others if getattr(event, name) is not None)
    if extra:
        raise RejectedMessage(
            RejectReason.UNKNOWN_FIELD, f"a {event.kind} event has no {', '.join(extra)}"
        )
    values = [event.timestamp, *(event.world_xy or ()), event.entered_at, event.dwell_s]
    if not all(value is None or abs(value) < float("inf") for value in values):
        raise RejectedMessage(RejectReason.INVALID_VALUE, "event times and places must be finite")


# --------------------------------------------------------------------------- live summary


class LiveCamera(msgspec.Struct, forbid_unknown_fields=True):
    """One camera's health in a live summary.

    Attributes:
        camera: the camera id.
        online: its last status said online (a last will or "offline" says not).
        received: messages received from it since the matcher started.
        rejected: of which refused by validation.
        rate_hz: messages per second over the last few seconds.
        last_capture: capture time of its newest message, seconds since the epoch.
        last_age_s: seconds since its last message arrived (None: none yet).
    """

    camera: CameraId
    online: bool
    received: Count
    rejected: Count
    rate_hz: float
    last_capture: float | None = None
    last_age_s: float | None = None


class LiveLine(msgspec.Struct, forbid_unknown_fields=True):
    """One counting line's totals in a live summary (both directions)."""
    line: PlaceName
    positive: Count
    negative: Count


class LiveZone(msgspec.Struct, forbid_unknown_fields=True):
    """A zone now and in total.

    Attributes:
        zone: its name.
        occupancy: confirmed tracks inside now.
        entries, exits, visits: totals since counting began.
        mean_dwell_s: mean dwell of the ended visits, seconds.
        dwell: ``[track, seconds so far]`` of the open visits (live dwell), longest first.
    """

    zone: PlaceName
    occupancy: Count
    entries: Count
    exits: Count
    visits: Count
    mean_dwell_s: float
    dwell: Annotated[list[tuple[int, float]], msgspec.Meta(max_length=1000)]


class LiveSummary(msgspec.Struct, forbid_unknown_fields=True):
    """A ``cblrs.live/1`` payload (see the module docstring).

    Attributes:
        clock: the analytics' clock (capture time they have counted up to), or None.
        sent_at: when the matcher published it, seconds since the epoch.
    """

    schema: str
    plane: SitePlaneId
    sent_at: float
    clock: float | None
    cameras: list[LiveCamera]
    lines: list[LiveLine]
    zones: list[LiveZone]


def encode_live(summary: dict[str, Any]) -> bytes:
    """Serialise a live summary (a dict with the :class:`LiveSummary` fields, no schema).

    Raises:
        RejectedMessage: it does not match the schema.
    """
    try:
        live = msgspec.convert({"schema": LIVE_SCHEMA, **summary}, LiveSummary)
    except msgspec.ValidationError as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    return msgspec.json.encode(live)


def decode_live(payload: bytes) -> LiveSummary:
    """Decode and validate a ``cblrs.live/1`` payload.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if len(payload) > MAX_LIVE_BYTES:
        raise RejectedMessage(RejectReason.OVERSIZED, f"live summary of {len(payload)} bytes")
    return _decode_typed(payload, LiveSummary, LIVE_SCHEMA)


# --------------------------------------------------------------------------- alerts

ALERTS_SCHEMA = "cblrs.alerts/1"
MAX_ALERT_BYTES = 64 * 1024
AlertName = Annotated[str, msgspec.Meta(min_length=1, max_length=256)]


class ActiveAlert(msgspec.Struct, forbid_unknown_fields=True):
    """An episode firing when the alert was published."""

    episode: AlertName
    rule: AlertName
    kind: AlertName
    subject: AlertName
    since: float | None
    value: float


class WireAlert(msgspec.Struct, forbid_unknown_fields=True):
    """A ``cblrs.alerts/1`` payload on ``cblrs/<plane>/alerts`` (QoS 1, retained): one
    episode fired or cleared (:class:`cblrs.alerts.AlertEvent`'s fields) and the episodes
    firing at publication (``active``), so that a viewer subscribing late sees them from the
    retained message. Subscribers de-duplicate on ``(episode, state)``."""

    schema: str
    plane: SitePlaneId
    episode: AlertName
    rule: AlertName
    kind: Literal["occupancy", "dwell", "line_count", "camera_offline", "matcher_lag"]
    subject: AlertName
    state: Literal["fired", "cleared"]
    timestamp: float
    since: float
    value: float
    threshold: float
    active: Annotated[list[ActiveAlert], msgspec.Meta(max_length=1000)]


def encode_alert(body: dict[str, Any], plane_id: int, active: list[dict[str, Any]]) -> bytes:
    """The payload of an alert (:meth:`cblrs.alerts.AlertEvent.to_dict`) with its plane and
    the episodes firing now.

    Raises:
        RejectedMessage: it would not pass :func:`decode_alert`.
    """
    document = {**body, "schema": ALERTS_SCHEMA, "plane": int(plane_id), "active": active}
    try:
        alert = msgspec.convert(document, WireAlert)
    except msgspec.ValidationError as error:
        raise RejectedMessage(RejectReason.INVALID_VALUE, str(error)) from None
    return msgspec.json.encode(alert)


def decode_alert(payload: bytes) -> WireAlert:
    """Decode and validate a ``cblrs.alerts/1`` payload.

    Raises:
        RejectedMessage: for every kind of bad input, and nothing else.
    """
    if len(payload) > MAX_ALERT_BYTES:
        raise RejectedMessage(RejectReason.OVERSIZED, f"alert of {len(payload)} bytes")
    return _decode_typed(payload, WireAlert, ALERTS_SCHEMA)
