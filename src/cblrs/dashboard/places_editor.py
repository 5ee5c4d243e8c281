"""The places editor's backend: the map's zones and counting lines, as the page edits them.

An admin draws, moves, renames and deletes zones and lines on the dashboard's map and saves
them; :func:`save_places` checks the whole list (names, geometry, closeness to the site's
planes), writes it into the site file's ``places:`` (the previous file kept as
``<site>.bak``) and reloads the file, so that what was written is known to load. Nothing is
written when any of it is refused, and the refusal is one sentence.

Only the places of the plane the dashboard shows are edited; places of the site's other
planes are kept as they are. A place's other settings (``hysteresis_m``, ``rule``,
``direction``, ``plane_id``) travel with it through the page and are written back unchanged.

The dashboard draws the saved places at once; the matcher's counts (zones entered, lines
crossed) come from ``cblrs matcher``, which reads the places when it starts: they follow the
new places after the matcher restarts.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError
from cblrs.names import name_problem
from cblrs.places import PlaceError, Places
from cblrs.site import Site, backup_document, load_site, save_document
from cblrs.site.core import site_from_document
from cblrs.site.schema import read_document

MAX_PLACES = 500
MAX_VERTICES = 200
NEAR_PLANE_M = 5.0
"""How far beyond a plane's rectangle (metres) a place's point may lie."""
MATCHER_NOTE = ("the map shows the new places now; the matcher reads places when it starts, "
                "so its counts follow them after cblrs matcher restarts.")

_ZONE_KEYS = {"name", "polygon", "plane_id", "hysteresis_m"}
_LINE_KEYS = {"name", "start", "end", "direction", "plane_id", "hysteresis_m", "rule"}


class PlacesEditError(CblrsError):
    """The page's places cannot be saved (one sentence for the page)."""


def site_version(site_path: Path) -> str:
    """A short digest of the site file: a save names the version it edited."""
    return hashlib.sha256(site_path.read_bytes()).hexdigest()[:16]


def shown_plane(site: Site, plane_id: int | None) -> int | None:
    """The plane the dashboard shows (the given one, else the site's first)."""
    planes = list(site.planes or [])
    return plane_id if plane_id is not None else (planes[0].plane_id if planes else None)


def places_view(site: Site, site_path: Path, plane_id: int | None) -> dict[str, Any]:
    """The editable places of the shown plane, as site-file data.

    Returns:
        ``{"plane", "zones": [zone data], "lines": [line data], "other": count of places on
        other planes (kept), "version", "near_m"}``.
    """
    plane = shown_plane(site, plane_id)
    zones = [zone.to_dict() for zone in site.places.zones if zone.plane_id in (None, plane)]
    lines = [line.to_dict() for line in site.places.lines if line.plane_id in (None, plane)]
    other = len(site.places) - len(zones) - len(lines)
    return {"plane": plane, "zones": zones, "lines": lines, "other": other,
            "version": site_version(site_path), "near_m": NEAR_PLANE_M}


def _point(value: Any, what: str) -> list[float]:
    if (not isinstance(value, list | tuple) or len(value) != 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) for v in value)):
        raise PlacesEditError(f"{what} must be a point [x, y] of two finite numbers (metres).")
    return [float(value[0]), float(value[1])]


def _named(item: Any, kind: str, index: int, allowed: set[str]) -> tuple[dict[str, Any], str]:
    if not isinstance(item, dict):
        raise PlacesEditError(f"{kind} {index + 1} must be an object with a name.")
    unknown = sorted(set(item) - allowed)
    if unknown:
        raise PlacesEditError(f"{kind} {index + 1} has an unknown key {unknown[0]!r} "
                              f"(allowed: {', '.join(sorted(allowed))}).")
    name = item.get("name")
    problem = name_problem(name)
    if problem is not None:
        shown = repr(name) if isinstance(name, str) else f"{index + 1}"
        raise PlacesEditError(f"{kind} name {shown} {problem}.")
    return dict(item), str(name)


def _check_near(points: list[list[float]], boxes: list[tuple[float, float, float, float]],
                what: str) -> None:
    if not boxes:
        return
    for number, (x, y) in enumerate(points, start=1):
        if not any(x0 - NEAR_PLANE_M <= x <= x1 + NEAR_PLANE_M
                   and y0 - NEAR_PLANE_M <= y <= y1 + NEAR_PLANE_M
                   for x0, y0, x1, y1 in boxes):
            raise PlacesEditError(
                f"{what}: point {number} ({x:.2f}, {y:.2f}) is more than {NEAR_PLANE_M:g} m "
                "outside the site's planes.")


def checked_places(site: Site, data: Any, plane_id: int | None) -> dict[str, list[dict]]:
    """The page's ``{"zones": [...], "lines": [...]}`` checked and merged with the places of
    the site's other planes: the site file's new ``places:`` section.

    Raises:
        PlacesEditError: a bad name, a duplicate, a degenerate or self-crossing zone, a line
            of one point, a point far from every plane, too many places (one sentence).
    """
    if not isinstance(data, dict):
        raise PlacesEditError("send {\"zones\": [...], \"lines\": [...]} as JSON.")
    zones, lines = data.get("zones", []), data.get("lines", [])
    if not isinstance(zones, list) or not isinstance(lines, list):
        raise PlacesEditError("zones and lines must be lists.")
    if len(zones) + len(lines) > MAX_PLACES:
        raise PlacesEditError(f"at most {MAX_PLACES} places may be saved at once.")
    plane = shown_plane(site, plane_id)
    several = len(list(site.planes or [])) > 1
    boxes = [(spec.origin[0], spec.origin[1], spec.origin[0] + spec.width,
              spec.origin[1] + spec.length) for spec in (site.planes or [])]
    seen: set[str] = set()

    def unique(name: str) -> None:
        if name in seen:
            raise PlacesEditError(f"two places are named {name!r}; names must be unique.")
        seen.add(name)

    new_zones, new_lines = [], []
    for index, item in enumerate(zones):
        zone, name = _named(item, "zone", index, _ZONE_KEYS)
        unique(name)
        polygon = zone.get("polygon")
        if not isinstance(polygon, list) or not 3 <= len(polygon) <= MAX_VERTICES:
            raise PlacesEditError(f"zone {name!r} needs 3 to {MAX_VERTICES} vertices.")
        zone["polygon"] = [_point(vertex, f"zone {name!r}: vertex {number + 1}")
                           for number, vertex in enumerate(polygon)]
        _check_near(zone["polygon"], boxes, f"zone {name!r}")
        if several and zone.get("plane_id") is None:
            zone["plane_id"] = plane
        new_zones.append(zone)
    for index, item in enumerate(lines):
        line, name = _named(item, "line", index, _LINE_KEYS)
        unique(name)
        line["start"] = _point(line.get("start"), f"line {name!r}: start")
        line["end"] = _point(line.get("end"), f"line {name!r}: end")
        if line.get("direction") is None:
            line.pop("direction", None)
        _check_near([line["start"], line["end"]], boxes, f"line {name!r}")
        if several and line.get("plane_id") is None:
            line["plane_id"] = plane
        new_lines.append(line)
    # Places of the other planes stay as they were (and keep their names).
    kept = site.places.to_dict()
    other_zones = [zone for zone in kept["zones"] if zone.get("plane_id") not in (None, plane)]
    other_lines = [line for line in kept["lines"] if line.get("plane_id") not in (None, plane)]
    for item in other_zones + other_lines:
        unique(item["name"])
    result = {"zones": other_zones + new_zones, "lines": other_lines + new_lines}
    try:
        Places.from_dict(result)  # geometry: >= 3 vertices, no self-crossing, length > 0
    except PlaceError as error:
        raise PlacesEditError(str(error)) from None
    return result


def save_places(site_path: Path, data: Any, plane_id: int | None) -> dict[str, Any]:
    """Write the page's places into the site file and reload it.

    Args:
        site_path: the site file (rewritten; the previous one is kept as ``<file>.bak``).
        data: ``{"zones": [{name, polygon, ...}], "lines": [{name, start, end, ...}],
            "version"}`` in site metres. Both lists are required (a body without them is
            refused, not read as "delete every place"); ``version`` (from
            :func:`places_view`), when given, must name the file as it is now (the page
            always gives it; a script may leave it out).
        plane_id: the plane the dashboard shows.

    Returns:
        ``{"site", "backup", "zones", "lines", "note"}`` (counts of the shown plane's places).

    Raises:
        PlacesEditError: the places are refused, or the file changed since the page read it
            (nothing written).
    """
    if not isinstance(data, dict) or not {"zones", "lines"} <= data.keys():
        raise PlacesEditError("a save gives both lists, \"zones\" and \"lines\" (empty to "
                              "delete every place of the plane); nothing written.")
    if data.get("version") not in (None, site_version(site_path)):
        raise PlacesEditError("the site file changed since this page read it; reload the page "
                              "and draw again.")
    site = load_site(site_path)
    places = checked_places(site, data, plane_id)
    document = read_document(site_path)
    if places["zones"] or places["lines"]:
        document["places"] = {key: value for key, value in places.items() if value}
    else:
        document.pop("places", None)
    try:
        site_from_document(document, site_path)  # alerts naming a deleted place, ...
    except CblrsError as error:
        raise PlacesEditError(f"not saved: {error}") from None
    backup = backup_document(site_path)  # no more open than the site file
    save_document(document, site_path)
    saved = load_site(site_path)  # what was written loads, or this raises
    plane = shown_plane(saved, plane_id)
    return {"site": str(site_path), "backup": str(backup),
            "zones": sum(zone.plane_id in (None, plane) for zone in saved.places.zones),
            "lines": sum(line.plane_id in (None, plane) for line in saved.places.lines),
            "note": MATCHER_NOTE}
