"""The parts of a site file the analytics need: name, planes' extents and places.

STOPGAP, to be replaced at merge: ``cblrs.site.load_site`` (the site schema, written in
parallel) reads and validates the whole file. Until it is on main, :func:`load_site_places`
reads only ``version``, ``name``, ``planes`` (extent) and ``places`` of the agreed layout
(YAML or JSON; ``cameras`` and ``map`` are accepted and left to the full loader). At merge,
build :class:`SitePlaces` from ``load_site(path)`` (``site.name``, ``site.planes``,
``site.places``) and delete the reader below.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.config import AnalyticsError
from cblrs.detections import Tracks
from cblrs.places import PlaceError, Places, bounding_box

_SECTIONS = {"version", "name", "planes", "cameras", "map", "places"}

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class SitePlaces:
    """What analytics read from a site file.

    Attributes:
        name: the site's name ("" when the file has none).
        places: its zones and counting lines.
        planes: (x_min, y_min, x_max, y_max) metres of each plane; empty without planes.
        source: the file it came from.
    """

    name: str
    places: Places
    planes: tuple[Bounds, ...]
    source: str


def load_site_places(path: str | Path) -> SitePlaces:
    """Read a site file's name, plane extents and places.

    Raises:
        AnalyticsError: missing or unreadable file, not YAML/JSON, wrong version, unknown
            top-level key, malformed planes or places (one sentence naming the file).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise AnalyticsError(f"site file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise AnalyticsError(f"cannot read site file {path}: {error}.") from None
    document = _parse(text, path)
    if not isinstance(document, dict):
        raise AnalyticsError(f"{path}: a site file is a mapping with version: 1 and sections.")
    unknown = sorted(set(document) - _SECTIONS)
    if unknown:
        raise AnalyticsError(
            f"{path}: {unknown[0]}: unknown key (allowed: {', '.join(sorted(_SECTIONS))})."
        )
    if document.get("version") != 1:
        raise AnalyticsError(f"{path}: version must be 1, got {document.get('version')!r}.")
    planes = []
    for index, plane in enumerate(document.get("planes") or []):
        try:
            (x, y), (width, length) = plane["origin"], plane["size"]
            bounds = (float(x), float(y), float(x) + float(width), float(y) + float(length))
        except (KeyError, TypeError, ValueError):
            raise AnalyticsError(
                f"{path}: planes[{index}] needs origin: [x, y] and size: [width, length]."
            ) from None
        if not (bounds[2] > bounds[0] and bounds[3] > bounds[1]):
            raise AnalyticsError(f"{path}: planes[{index}] needs a positive size.")
        planes.append(bounds)
    try:
        places = Places.from_dict(document.get("places") or {})
    except PlaceError as error:
        raise AnalyticsError(f"{path}: {error}") from None
    return SitePlaces(str(document.get("name") or ""), places, tuple(planes), str(path))


def _parse(text: str, path: Path) -> Any:
    if path.suffix.lower() == ".json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as error:
            raise AnalyticsError(
                f"{path} is not valid JSON: {error.msg} (line {error.lineno})."
            ) from None
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise AnalyticsError(f"{path} is not valid YAML{where}.") from None


def site_extent(site: SitePlaces) -> Bounds:
    """The area the site covers: its planes, or without planes its places' bounding box."""
    boxes = list(site.planes)
    if not boxes:
        places_box = bounding_box(site.places)
        if places_box is None:
            raise AnalyticsError(f"{site.source} has no places and no planes.")
        boxes = [places_box]
    array = np.array(boxes)
    return (float(array[:, 0].min()), float(array[:, 1].min()),
            float(array[:, 2].max()), float(array[:, 3].max()))


def check_tracks_on_site(tracks: Tracks, site: SitePlaces, tolerance_m: float = 2.0) -> int:
    """Refuse tracks that do not belong to the site; return how many rows lie outside it.

    With planes, a position belongs when it lies on a plane (within ``tolerance_m``: a
    tracker's filter may overshoot a plane's edge a little). Without planes the site is
    known only by its places, so a position belongs when it lies within the places'
    bounding box grown by its own size (at least 10 m) on every side.

    Raises:
        AnalyticsError: more than half of the positions lie outside the site.
    """
    if len(tracks) == 0:
        return 0
    xy = tracks.world_xy
    if site.planes:
        inside = np.zeros(len(xy), dtype=bool)
        for x0, y0, x1, y1 in site.planes:
            inside |= ((xy[:, 0] >= x0 - tolerance_m) & (xy[:, 0] <= x1 + tolerance_m)
                       & (xy[:, 1] >= y0 - tolerance_m) & (xy[:, 1] <= y1 + tolerance_m))
        what = "every plane of"
    else:
        x0, y0, x1, y1 = site_extent(site)
        grow = max(10.0, x1 - x0, y1 - y0)
        inside = ((xy[:, 0] >= x0 - grow) & (xy[:, 0] <= x1 + grow)
                  & (xy[:, 1] >= y0 - grow) & (xy[:, 1] <= y1 + grow))
        what = "the places of"
    outside = int(np.count_nonzero(~inside))
    if outside * 2 > len(xy):
        centre = np.median(xy, axis=0)
        raise AnalyticsError(
            f"{outside} of {len(xy)} track positions (median at x={centre[0]:.1f}, "
            f"y={centre[1]:.1f} m) lie outside {what} site {site.name or site.source}: "
            "are these tracks from another site?"
        )
    return outside
