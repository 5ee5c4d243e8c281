"""Where tracks pass between planes: overlap bands and portals (the site file's ``links``).

A link joins two planes. Either the planes **overlap** (the same height, rectangles that
intersect): both planes' cameras see the band where they meet, so a person walking from one
into the other is tracked by both matchers for a while and handed over there; or the link
has two **portals**, one polygon on each plane, where tracks leave one plane and appear on the
other some seconds later (stairs between two levels, a stretch of street no camera sees).

These are pure geometry (metres, the site's world frame); :class:`~cblrs.linking.PlaneLinker`
links with them.

Example:
    >>> from cblrs.plane import PlaneSpec
    >>> west, east = PlaneSpec(1, (0, 0), 40, 30), PlaneSpec(2, (34, 0), 40, 30)
    >>> link = PlaneLink.overlap(west, east)
    >>> link.region_of(2).contains([[36.0, 10.0], [50.0, 10.0]]).tolist()
    [True, False]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cblrs.errors import CblrsError
from cblrs.places import PlaceError, Zone
from cblrs.plane import PlaneSet, PlaneSpec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

OVERLAP_TRANSIT_S = (0.0, 3.0)
"""How long a track may be unseen between leaving one overlapping plane and appearing on the
other (seconds): a person the second plane's cameras pick up a moment after the first lost
them is still handed over."""

REACH_M = 3.0
"""How far beyond an overlap band (metres) a track may start and still be handed over: the
second plane's cameras may find a person only a few steps after the band."""

PORTAL_REACH_M = 3.0
"""How far outside a portal (metres) a track may start or end and still pass through it: a
tracker's estimate runs a little past the last colour its plane has (about 1 m), and a
vehicle's track is its footprint centre, up to half its length (2.25 m for a car) from the
ground point its box's colour gave (:mod:`cblrs.matching.fusion.footprint`). Measured on the
street of ``cblrs experiment planes`` (exact boxes): with 1 m, three cars' portal hand-overs
were missed once the footprint stage moved their tracks (OD error 6.2 %); with 3 m none."""


class LinkError(CblrsError):
    """A link between planes is inconsistent with the planes it joins."""


@dataclass(frozen=True)
class PlaneLink:
    """A hand-over between two planes.

    Attributes:
        planes: the two plane ids (distinct).
        regions: per plane (same order), the polygon where its tracks are handed over: the
            overlap band widened by :data:`REACH_M` (overlap) or the plane's portal.
        portal: True for a portal link (the planes do not see the same ground).
        transit_s: (min, max) seconds between a track's last row on one plane and its first
            on the other (0 when both see it at once).
        max_distance_m: overlap: the largest mean distance between the two planes' rows of
            one person seen by both (or between where the first plane's track was heading
            and where the second's starts); portal: unused.
    """

    planes: tuple[int, int]
    regions: tuple[Zone, Zone]
    portal: bool
    transit_s: tuple[float, float]
    max_distance_m: float = 1.5

    def __post_init__(self) -> None:
        first, second = self.planes
        if first == second:
            raise LinkError(f"a link joins two different planes, got {first} twice.")
        low, high = self.transit_s
        if not 0 <= low <= high:
            raise LinkError(f"transit_s must be 0 <= min <= max seconds, got {self.transit_s}.")
        if not self.max_distance_m > 0:
            raise LinkError(f"max_distance_m must be positive, got {self.max_distance_m}.")

    @classmethod
    def overlap(
        cls,
        first: PlaneSpec,
        second: PlaneSpec,
        max_distance_m: float = 1.5,
        transit_s: tuple[float, float] = OVERLAP_TRANSIT_S,
    ) -> PlaneLink:
        """The link of two planes whose rectangles overlap at the same height.

        Raises:
            LinkError: the planes are at different heights or do not overlap.
        """
        if first.height != second.height:
            raise LinkError(
                f"planes {first.plane_id} and {second.plane_id} are at different heights "
                f"({first.height} and {second.height} m), so they cannot overlap; give the "
                "link portals (where tracks leave one plane and enter the other)."
            )
        low = np.maximum(first.origin, second.origin)
        high = np.minimum(
            np.add(first.origin, (first.width, first.length)),
            np.add(second.origin, (second.width, second.length)),
        )
        if not np.all(high > low):
            raise LinkError(
                f"planes {first.plane_id} and {second.plane_id} do not overlap; give the link "
                "portals (where tracks leave one plane and enter the other)."
            )
        x0, y0 = (low - REACH_M).tolist()
        x1, y1 = (high + REACH_M).tolist()
        band = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
        name = f"overlap {first.plane_id}-{second.plane_id}"
        region = Zone(name, np.array(band))
        return cls((first.plane_id, second.plane_id), (region, region), False,
                   (float(transit_s[0]), float(transit_s[1])), float(max_distance_m))

    @classmethod
    def through_portals(
        cls,
        planes: tuple[int, int],
        portals: Sequence[ArrayLike],
        transit_s: tuple[float, float] = (0.0, 30.0),
        max_distance_m: float = 1.5,
    ) -> PlaneLink:
        """A portal link: ``portals[i]`` is a polygon (metres) on plane ``planes[i]``."""
        if len(portals) != 2:
            raise LinkError("a portal link needs two polygons, one on each plane.")
        regions = []
        for plane_id, polygon in zip(planes, portals, strict=True):
            try:
                regions.append(Zone(f"portal of plane {plane_id}", np.asarray(polygon, float)))
            except PlaceError as error:
                raise LinkError(str(error)) from None
        return cls((int(planes[0]), int(planes[1])), (regions[0], regions[1]), True,
                   (float(transit_s[0]), float(transit_s[1])), float(max_distance_m))

    def other(self, plane_id: int) -> int:
        """The plane at the other end of the link from ``plane_id``."""
        first, second = self.planes
        if plane_id == first:
            return second
        if plane_id == second:
            return first
        raise LinkError(f"plane {plane_id} is not on the link {first}-{second}.")

    def region_of(self, plane_id: int) -> Zone:
        """The polygon where tracks of ``plane_id`` are handed over on this link."""
        if plane_id not in self.planes:
            raise LinkError(f"plane {plane_id} is not on the link {self.planes}.")
        return self.regions[self.planes.index(plane_id)]

    def in_region(self, plane_id: int, world_xy: ArrayLike) -> BoolArray:
        """Which points (N, 2) metres lie in ``plane_id``'s hand-over region (a portal's
        within :data:`PORTAL_REACH_M` of it)."""
        region = self.region_of(plane_id)
        if not self.portal:
            return region.contains(world_xy)
        return region.signed_distance(world_xy) >= -PORTAL_REACH_M

    def to_dict(self) -> dict:
        """The link as site-file data (the inverse of :func:`links_from_site`'s reading)."""
        data: dict = {"planes": list(self.planes)}
        if self.portal:
            data["portals"] = [region.polygon.tolist() for region in self.regions]
            data["transit_s"] = list(self.transit_s)
        elif self.transit_s != OVERLAP_TRANSIT_S:
            data["transit_s"] = list(self.transit_s)
        if self.max_distance_m != 1.5:
            data["max_distance_m"] = self.max_distance_m
        return data


def build_links(items: Sequence[dict], planes: PlaneSet) -> tuple[PlaneLink, ...]:
    """Links from site-file data (``links:``), checked against the site's planes.

    Args:
        items: validated link mappings: ``planes``, optional ``portals``, ``transit_s``,
            ``max_distance_m``.
        planes: the site's planes.

    Raises:
        LinkError: a plane that does not exist, a pair linked twice, overlapping planes that
            do not overlap, a portal that is not on its plane.
    """
    links = []
    seen: dict[frozenset[int], int] = {}
    for index, item in enumerate(items):
        where = f"links[{index}]"
        pair = tuple(int(plane) for plane in item["planes"])
        for plane_id in pair:
            if plane_id not in planes.ids:
                raise LinkError(f"{where}: no plane {plane_id} (planes: {planes.ids}).")
        key = frozenset(pair)
        if key in seen:
            raise LinkError(f"{where}: planes {pair[0]} and {pair[1]} are already linked by "
                            f"links[{seen[key]}].")
        seen[key] = index
        distance = float(item.get("max_distance_m", 1.5))
        portals = item.get("portals")
        try:
            if portals is None:
                transit = item.get("transit_s")
                link = PlaneLink.overlap(
                    planes.by_id(pair[0]), planes.by_id(pair[1]), distance,
                    OVERLAP_TRANSIT_S if transit is None else (transit[0], transit[1]),
                )
            else:
                transit = item.get("transit_s") or (0.0, 30.0)
                link = PlaneLink.through_portals(
                    (pair[0], pair[1]), portals, (transit[0], transit[1]), distance
                )
                for plane_id, region in zip(pair, link.regions, strict=True):
                    plane = planes.by_id(plane_id)
                    if not plane.contains(region.polygon).any():
                        raise LinkError(
                            f"the portal on plane {plane_id} has no corner on that plane "
                            f"({plane.origin[0]:g}, {plane.origin[1]:g}, {plane.width:g} x "
                            f"{plane.length:g} m)."
                        )
        except LinkError as error:
            text = str(error)
            raise LinkError(text if text.startswith(where) else f"{where}: {text}") from None
        links.append(link)
    return tuple(links)
