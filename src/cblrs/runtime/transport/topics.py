"""MQTT topic names of the runtime, and the camera ids that may appear in them.

Layout (one subtree per plane, so a broker cluster can be split by plane id)::

    cblrs/<plane>/<camera>/detections        camera -> matcher, QoS 1
    cblrs/<plane>/<camera>/status            retained availability, last will "offline"
    cblrs/<plane>/<camera>/stored            matcher -> camera: sequences stored (or rejected)
    cblrs/<plane>/tracks                     matcher -> viewers, track updates
    cblrs/<plane>/events                     matcher -> viewers, analytics events (QoS 1)
    cblrs/<plane>/live                       matcher -> viewers, counts and camera health (1 Hz)
    cblrs/<plane>/alerts                     matcher -> viewers, alert episodes (QoS 1, retained)
    cblrs/<plane>/matchers/<matcher>/status  retained availability of a matcher
    cblrs/<plane>/lease                      retained: which matcher instance holds the plane
    cblrs/0/tracks                           linker -> viewers, global tracks of the site
    cblrs/0/events                           linker -> viewers, the site's analytics events
    cblrs/0/live                             linker -> viewers, the site's counts (1 Hz)
                                             (events_topic(0), live_topic(0))
    cblrs/0/linkers/<linker>/status          retained availability of a linker

``<plane>`` is the decimal plane id (the B channel of the reference colours); 0, the B
channel's "no plane", names the whole site (:data:`SITE_PLANE`).
"""

from __future__ import annotations

import functools
import re

from cblrs.errors import CblrsError

ROOT = "cblrs"
MAX_ID_LENGTH = 64
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}\Z"
"""Camera and matcher ids: letters, digits, ``_ . -``; no MQTT wildcards, ``/`` or ``$``.
Anchored with ``\\Z``, not ``$``: ``$`` also matches before a trailing newline, so
``"CVLab1\\n"`` would pass (msgspec applies the pattern with ``re.search``)."""

_ID = re.compile(ID_PATTERN)
MAX_PLANE_ID = 65535
SITE_PLANE = 0
"""The "plane" of the whole site in topics: the linker's global tracks and analytics."""


class TopicError(CblrsError):
    """A camera id, plane id or topic is not usable in the runtime's topic layout."""


def validate_client_id(name: str, what: str = "camera id") -> str:
    """Return ``name`` if it can be one level of a topic, else raise :class:`TopicError`.

    Args:
        name: a camera or matcher id.
        what: how to call it in the error message.
    """
    if not isinstance(name, str) or not _ID.fullmatch(name):
        raise TopicError(
            f"{what} {name!r} is not usable in MQTT topics: use 1 to {MAX_ID_LENGTH} letters, "
            "digits, '_', '.' or '-', starting with a letter or digit."
        )
    return name


def validate_camera_id(camera_id: str) -> str:
    """Return ``camera_id`` if it is a valid topic level (see :data:`ID_PATTERN`)."""
    return validate_client_id(camera_id, "camera id")


def _plane(plane_id: int) -> str:
    if isinstance(plane_id, bool) or not isinstance(plane_id, int):
        raise TopicError(f"plane id must be an integer, got {plane_id!r}.")
    if not 1 <= plane_id <= MAX_PLANE_ID:
        raise TopicError(f"plane id must be 1..{MAX_PLANE_ID}, got {plane_id}.")
    return str(plane_id)


def detections_topic(plane_id: int, camera_id: str) -> str:
    """``cblrs/<plane>/<camera>/detections``."""
    return f"{ROOT}/{_plane(plane_id)}/{validate_camera_id(camera_id)}/detections"


def status_topic(plane_id: int, camera_id: str) -> str:
    """``cblrs/<plane>/<camera>/status``: retained "online"/"offline" of a camera."""
    return f"{ROOT}/{_plane(plane_id)}/{validate_camera_id(camera_id)}/status"


def matcher_status_topic(plane_id: int, matcher_id: str) -> str:
    """``cblrs/<plane>/matchers/<matcher>/status``: retained availability of a matcher."""
    matcher = validate_client_id(matcher_id, "matcher id")
    return f"{ROOT}/{_plane(plane_id)}/matchers/{matcher}/status"


def matcher_status_filter(plane_id: int) -> str:
    """Subscription filter for the status of every matcher of a plane."""
    return f"{ROOT}/{_plane(plane_id)}/matchers/+/status"


def lease_topic(plane_id: int) -> str:
    """``cblrs/<plane>/lease``: retained record of the matcher instance serving the plane."""
    return f"{ROOT}/{_plane(plane_id)}/lease"


def stored_topic(plane_id: int, camera_id: str) -> str:
    """``cblrs/<plane>/<camera>/stored``: the matcher's confirmations to one camera."""
    return f"{ROOT}/{_plane(plane_id)}/{validate_camera_id(camera_id)}/stored"


def tracks_topic(plane_id: int) -> str:
    """``cblrs/<plane>/tracks``: track updates published by the plane's matcher."""
    return f"{ROOT}/{_plane(plane_id)}/tracks"


def events_topic(plane_id: int) -> str:
    """``cblrs/<plane>/events``: analytics events (line crossings, zone entries and exits);
    plane 0: the site's (counted by the linker on the global tracks)."""
    return f"{ROOT}/{_plane_or_site(plane_id)}/events"


def live_topic(plane_id: int) -> str:
    """``cblrs/<plane>/live``: the matcher's live summary (counts, occupancy, camera health);
    plane 0: the linker's summary of the site."""
    return f"{ROOT}/{_plane_or_site(plane_id)}/live"


def alerts_topic(plane_id: int) -> str:
    """``cblrs/<plane>/alerts``: alert episodes fired and cleared (:mod:`cblrs.alerts`),
    each with the episodes firing then; retained, so a viewer that subscribes late sees them."""
    return f"{ROOT}/{_plane(plane_id)}/alerts"


def _plane_or_site(plane_id: int) -> str:
    return str(SITE_PLANE) if plane_id == SITE_PLANE and not isinstance(plane_id, bool) else (
        _plane(plane_id))


def site_tracks_topic() -> str:
    """``cblrs/0/tracks``: the linker's global tracks (ids across planes)."""
    return f"{ROOT}/{SITE_PLANE}/tracks"


def linker_status_topic(linker_id: str) -> str:
    """``cblrs/0/linkers/<linker>/status``: retained availability of a linker."""
    return f"{ROOT}/{SITE_PLANE}/linkers/{validate_client_id(linker_id, 'linker id')}/status"


def linker_status_filter() -> str:
    """Subscription filter for the status of every linker of the site."""
    return f"{ROOT}/{SITE_PLANE}/linkers/+/status"


def parse_tracks_topic(topic: str) -> int:
    """``cblrs/<plane>/tracks`` -> the plane id (0: the site's global tracks).

    Raises:
        TopicError: the topic does not have that form.
    """
    parts = topic.split("/")
    if len(parts) != 3 or parts[0] != ROOT or parts[2] != "tracks":
        raise TopicError(f"{topic!r} is not a tracks topic (cblrs/<plane>/tracks).")
    if not parts[1].isdigit() or parts[1] != str(int(parts[1])):
        raise TopicError(f"{topic!r} has no decimal plane id.")
    plane_id = int(parts[1])
    if plane_id != SITE_PLANE:
        _plane(plane_id)
    return plane_id


def detections_filter(plane_id: int | None = None) -> str:
    """Subscription filter for the detections of every camera of a plane (or of all planes)."""
    plane = "+" if plane_id is None else _plane(plane_id)
    return f"{ROOT}/{plane}/+/detections"


def status_filter(plane_id: int | None = None) -> str:
    """Subscription filter for the status of every camera of a plane (or of all planes)."""
    plane = "+" if plane_id is None else _plane(plane_id)
    return f"{ROOT}/{plane}/+/status"


def parse_detections_topic(topic: str) -> tuple[int, str]:
    """``cblrs/<plane>/<camera>/detections`` -> ``(plane_id, camera_id)``.

    Raises:
        TopicError: the topic does not have that form.
    """
    parts = topic.split("/")
    if len(parts) != 4 or parts[0] != ROOT or parts[3] != "detections":
        raise TopicError(
            f"{topic!r} is not a detections topic (cblrs/<plane>/<camera>/detections)."
        )
    plane_text, camera_id = parts[1], parts[2]
    if not plane_text.isdigit() or plane_text != str(int(plane_text)):
        raise TopicError(f"{topic!r} has no decimal plane id.")
    plane_id = int(plane_text)
    _plane(plane_id)
    validate_camera_id(camera_id)
    return plane_id, camera_id


def parse_status_topic(topic: str) -> tuple[int, str]:
    """``cblrs/<plane>/<camera>/status`` -> ``(plane_id, camera_id)``."""
    parts = topic.split("/")
    if len(parts) != 4 or parts[0] != ROOT or parts[3] != "status":
        raise TopicError(f"{topic!r} is not a camera status topic (cblrs/<plane>/<camera>/status).")
    return parse_detections_topic(f"{ROOT}/{parts[1]}/{parts[2]}/detections")


@functools.lru_cache(maxsize=4096)
def topic_matches(topic_filter: str, topic: str) -> bool:
    """MQTT filter matching with ``+`` (one level) and ``#`` (the rest, incl. the parent).

    Topics starting with ``$`` are not matched by filters starting with a wildcard.
    """
    if topic.startswith("$") and topic_filter[:1] in ("+", "#"):
        return False
    filter_levels = topic_filter.split("/")
    topic_levels = topic.split("/")
    for index, level in enumerate(filter_levels):
        if level == "#":
            return True
        if index >= len(topic_levels):
            return False
        if level != "+" and level != topic_levels[index]:
            return False
    return len(filter_levels) == len(topic_levels)


def filters_overlap(first: str, second: str) -> bool:
    """Whether some topic matches both subscription filters."""
    first_levels, second_levels = first.split("/"), second.split("/")
    for index in range(max(len(first_levels), len(second_levels))):
        a = first_levels[index] if index < len(first_levels) else None
        b = second_levels[index] if index < len(second_levels) else None
        if a == "#" or b == "#":
            return True  # "x/#" also matches "x" itself
        if a is None or b is None:
            return False
        if a != b and a != "+" and b != "+":
            return False
    return True


def validate_filter(topic_filter: str) -> str:
    """Return ``topic_filter`` if it is a valid MQTT subscription filter."""
    levels = topic_filter.split("/")
    if not topic_filter or "\x00" in topic_filter:
        raise TopicError(f"invalid topic filter {topic_filter!r}.")
    for index, level in enumerate(levels):
        if "#" in level and (level != "#" or index != len(levels) - 1):
            raise TopicError(f"'#' must be the last level of a filter: {topic_filter!r}.")
        if "+" in level and level != "+":
            raise TopicError(f"'+' must be a whole level of a filter: {topic_filter!r}.")
    return topic_filter


def validate_topic(topic: str) -> str:
    """Return ``topic`` if it is a valid topic to publish on (no wildcards)."""
    if not topic or "+" in topic or "#" in topic or "\x00" in topic:
        raise TopicError(f"invalid topic to publish on {topic!r}.")
    return topic
