"""What the analytics read from a site file, and the check that tracks belong to it.

The site file itself is read and validated by :func:`cblrs.site.load_site`; here it is
reduced to what counting needs: the name, the places, the planes' extents (the heatmap grid
and the "tracks from another site" check) and the site map (drawn under the heatmap).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.config import AnalyticsConfig, AnalyticsError
from cblrs.detections import Tracks
from cblrs.places import Places, bounding_box
from cblrs.site import load_site

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class SitePlaces:
    """What analytics read from a site file.

    Attributes:
        name: the site's name ("" when the file has none).
        places: its zones and counting lines.
        planes: (x_min, y_min, x_max, y_max) metres of each plane; empty without planes.
        source: the file it came from.
        map_image: the site map's image file, if the site has one.
        map_extent: (x_min, x_max, y_min, y_max) metres the map image covers (``imshow``).
        timezone: the site's IANA time zone (None: none given).
        opening_hours: its opening hours as written in the file (None: always open).
    """

    name: str
    places: Places
    planes: tuple[Bounds, ...]
    source: str
    map_image: Path | None = None
    map_extent: tuple[float, float, float, float] | None = None
    timezone: str | None = None
    opening_hours: dict[str, Any] | None = None


def load_site_places(path: str | Path) -> SitePlaces:
    """Read a site file (:func:`cblrs.site.load_site`) for the analytics.

    Raises:
        cblrs.site.SiteError: the file is missing, malformed or invalid (one sentence).
    """

    site = load_site(path)
    planes = tuple(
        (plane.origin[0], plane.origin[1], plane.origin[0] + plane.width,
         plane.origin[1] + plane.length)
        for plane in (site.planes or [])
    )
    image, extent = None, None
    if site.map is not None and site.map.image is not None and site.map.image.is_file():
        # lazy: OpenCV takes ~80 ms to import; only this path needs it
        import cv2

        picture = cv2.imread(str(site.map.image), cv2.IMREAD_UNCHANGED)
        if picture is not None:
            height, width = picture.shape[:2]
            corners = site.map.to_world(np.array([[0.0, 0.0], [width, height]]))
            image = site.map.image
            extent = (float(corners[0, 0]), float(corners[1, 0]),
                      float(corners[1, 1]), float(corners[0, 1]))
    return SitePlaces(site.name or "", site.places, planes, str(path), image, extent,
                      site.model.timezone, site.model.opening_hours)


def with_site_time(config: AnalyticsConfig, site: Any) -> AnalyticsConfig:
    """``config`` with the time zone and opening hours of a site (a :class:`SitePlaces` or a
    :class:`cblrs.site.Site`); unchanged when the site has no time zone."""
    model = getattr(site, "model", site)
    if model.timezone is None:
        return config
    return replace(config, timezone=model.timezone, opening_hours=model.opening_hours)


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
