"""NATS subjects, stream names and message ids of the cblrs backbone (no connection here).

What both sides of a NATS deployment must agree on, without the nats-py client: how an MQTT
topic maps onto a NATS subject (exactly as the NATS server's MQTT listener maps it), the site
prefix that lets several sites share one cluster, each plane's two streams and which subjects
they keep, the lease keys, and the ``Nats-Msg-Id`` by which JetStream stores a re-sent
publish once. :mod:`~cblrs.runtime.transport.nats_transport` publishes and subscribes with
them; :mod:`~cblrs.runtime.broker.nats_auth` writes the logins' permissions from them.

Example:
    >>> site_subject("cblrs/1/cam.A/detections", "north")
    'cblrs.north.1.cam//A.detections'
    >>> stream_of("cblrs.north.1.cam//A.detections", "north")
    'CBLRS_north_P1'
"""

from __future__ import annotations

import functools
import re

import msgspec

from cblrs.runtime.transport.protocol import TransportError
from cblrs.runtime.transport.topics import MAX_PLANE_ID, ROOT, topic_matches

LEGACY_DETECTIONS_STREAM = "CBLRS"
"""The one stream of every plane that cblrs before per-plane streams created (still used by a
deployment that has it; see :meth:`NatsTransport._resolve_stream`)."""
LEGACY_TRACKS_STREAM = "CBLRS_TRACKS"
LEASE_BUCKET = "cblrs_leases"
SITE_PATTERN = r"[A-Za-z][A-Za-z0-9-]{0,31}"
"""Site ids: a letter, then letters, digits or ``-`` (never a plane's decimal token, never a
character a stream name forbids)."""
_SITE = re.compile(SITE_PATTERN)

@functools.lru_cache(maxsize=4096)
def topic_to_subject(topic: str) -> str:
    """An MQTT topic (or filter) as the NATS subject the server's MQTT listener uses."""
    levels = []
    for level in topic.split("/"):
        if level == "+":
            levels.append("*")
        elif level == "#":
            levels.append(">")
        else:
            levels.append(level.replace(".", "//"))
    return ".".join(levels)


@functools.lru_cache(maxsize=4096)
def subject_to_topic(subject: str) -> str:
    """The MQTT topic of a NATS subject (inverse of :func:`topic_to_subject`)."""
    return "/".join(token.replace("//", ".") for token in subject.split("."))


def subject_matches(pattern: str, subject: str) -> bool:
    """NATS subject matching with ``*`` (one token) and ``>`` (one or more tokens)."""
    return topic_matches(
        subject_to_topic(pattern.replace(">", "#").replace("*", "+")), subject_to_topic(subject)
    )


def validate_site(site: str) -> str:
    """Return ``site`` if it is a usable site id (see :data:`SITE_PATTERN`), else raise."""
    if not isinstance(site, str) or not _SITE.fullmatch(site):
        raise TransportError(
            f"site id {site!r} is not usable: use a letter, then up to 31 letters, digits or "
            "'-'."
        )
    return site


def subject_root(site: str | None = None) -> str:
    """``cblrs`` (no site: the layout of a cluster with one site) or ``cblrs.<site>``."""
    return ROOT if site is None else f"{ROOT}.{site}"


@functools.lru_cache(maxsize=4096)
def site_subject(topic: str, site: str | None = None) -> str:
    """The subject of an MQTT topic (or filter) for ``site``: ``cblrs/1/c/detections`` is
    ``cblrs.<site>.1.c.detections`` (``cblrs.1.c.detections`` without a site)."""
    subject = topic_to_subject(topic)
    if site is None:
        return subject
    head, dot, rest = subject.partition(".")
    return f"{ROOT}.{site}{dot}{rest}" if head == ROOT else subject


@functools.lru_cache(maxsize=4096)
def site_topic(subject: str, site: str | None = None) -> str:
    """The MQTT topic of a subject of ``site`` (inverse of :func:`site_subject`)."""
    if site is not None and subject.startswith(f"{ROOT}.{site}."):
        subject = ROOT + subject[len(ROOT) + len(site) + 1:]
    return subject_to_topic(subject)


def detections_stream(plane_id: int, site: str | None = None) -> str:
    """The stream of one plane's detections and camera status: ``CBLRS_P<plane>`` or
    ``CBLRS_<site>_P<plane>``."""
    return f"CBLRS_P{plane_id}" if site is None else f"CBLRS_{site}_P{plane_id}"


def tracks_stream(plane_id: int, site: str | None = None) -> str:
    """The stream of one plane's track updates, analytics events and alerts."""
    return detections_stream(plane_id, site) + "_TRACKS"


def stream_subjects(stream: str, plane_id: int, site: str | None = None) -> list[str]:
    """The subjects ``stream`` (one of a plane's two) stores."""
    root = subject_root(site)
    if stream == tracks_stream(plane_id, site):
        return [f"{root}.{plane_id}.tracks", f"{root}.{plane_id}.events",
                f"{root}.{plane_id}.alerts"]
    return [f"{root}.{plane_id}.*.detections", f"{root}.{plane_id}.*.status"]


def lease_key(plane_id: int, site: str | None = None) -> str:
    """The plane's key in the lease bucket: ``plane-<plane>`` or ``<site>.plane-<plane>``."""
    return f"plane-{plane_id}" if site is None else f"{site}.plane-{plane_id}"


def _classify(subject: str, site: str | None) -> tuple[str, int] | None:
    """``("detections" | "tracks", plane)`` for a subject (or filter) a plane's stream holds."""
    root = subject_root(site) + "."
    if not subject.startswith(root):
        return None
    tokens = subject[len(root):].split(".")
    plane = tokens[0]
    if not plane.isdigit() or plane != str(int(plane)) or not 1 <= int(plane) <= MAX_PLANE_ID:
        return None
    if len(tokens) == 3 and tokens[2] in ("detections", "status"):
        return "detections", int(plane)
    if len(tokens) == 2 and tokens[1] in ("tracks", "events", "alerts"):
        return "tracks", int(plane)
    return None


def stream_of(subject: str, site: str | None = None) -> str | None:
    """The stream that stores ``subject`` (a plane's detections or tracks stream), or None
    (a plain NATS subject, e.g. a matcher's status or the live summary)."""
    kind = _classify(subject, site)
    if kind is None:
        return None
    maker = detections_stream if kind[0] == "detections" else tracks_stream
    return maker(kind[1], site)


class _MessageKey(msgspec.Struct):
    camera: str
    sequence: int
    plane: int


class _TrackRow(msgspec.Struct):
    timestamp: float


class _TracksKey(msgspec.Struct):
    plane: int
    tracks: list[_TrackRow]


class _EventKey(msgspec.Struct):
    plane: int
    key: str


class _AlertKey(msgspec.Struct):
    plane: int
    episode: str
    state: str


_message_key = msgspec.json.Decoder(_MessageKey)
_tracks_key = msgspec.json.Decoder(_TracksKey)
_event_key = msgspec.json.Decoder(_EventKey)
_alert_key = msgspec.json.Decoder(_AlertKey)


def message_id(subject: str, payload: bytes) -> str | None:
    """The ``Nats-Msg-Id`` a publish on ``subject`` carries, or None.

    Detections: ``<plane>.<camera>.<sequence>`` (the matcher's de-duplication key too); track
    updates: ``tracks.<plane>.<capture timestamp>`` (one update per plane and timestamp
    group), so a matcher that re-tracks groups after a failover does not store them twice;
    analytics events: ``events.<plane>.<key>`` (the event's natural identity), so an event
    published again (after a matcher restart, or counted again by a rebuilt plane) is stored
    once; alerts: ``alerts.<plane>.<episode>.<state>`` (what receivers de-duplicate on), so
    an alert published again after a lost acknowledgement is stored once.
    """
    try:
        if subject.endswith(".detections"):
            key = _message_key.decode(payload)
            return f"{key.plane}.{key.camera}.{key.sequence}"
        if subject.endswith(".tracks"):
            update = _tracks_key.decode(payload)
            if update.tracks:
                return f"tracks.{update.plane}.{update.tracks[0].timestamp!r}"
        if subject.endswith(".events"):
            event = _event_key.decode(payload)
            return f"events.{event.plane}.{event.key}"
        if subject.endswith(".alerts"):
            alert = _alert_key.decode(payload)
            return f"alerts.{alert.plane}.{alert.episode}.{alert.state}"
    except msgspec.DecodeError:
        return None  # the matcher rejects and counts it; nothing to de-duplicate by
    return None
