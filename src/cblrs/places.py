"""Named places on the ground plane: zones and counting lines (metres).

Places are what operators count against: a **zone** is a simple polygon (occupancy, entries,
exits, dwell), a **counting line** is a segment with a positive direction (crossings per
direction). They are pure geometry in world metres; the site file (:mod:`cblrs.site`) reads
them and the analytics (:mod:`cblrs.analytics`) count with them.

Example:
    >>> line = CountingLine("gate", start=(0.0, 0.0), end=(0.0, 4.0))
    >>> line.signed_distance([[1.0, 2.0], [-1.0, 2.0]])  # positive: left of start -> end
    array([-1.,  1.])
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cblrs.errors import CblrsError
from cblrs.names import name_problem

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class PlaceError(CblrsError):
    """A zone or counting line is invalid (self-intersecting, degenerate, duplicated)."""


class LineRule(StrEnum):
    """What counts as crossing a counting line.

    ``hysteresis`` (cblrs' default): the track goes from farther than the hysteresis on one
    side to farther than it on the other, and crosses the segment itself on the way; jitter
    near the line and passing beyond its ends count nothing.

    ``side_change``: the rule of common tools (supervision's ``LineZone``, the usual
    tripwire): a crossing whenever the side of the line changes between two positions that
    both lie within the segment's extent (between the perpendiculars through its ends),
    however little the track moved.
    """

    HYSTERESIS = "hysteresis"
    SIDE_CHANGE = "side_change"


def line_rule_text(rule: LineRule | str, hysteresis_m: float) -> str:
    """A short label of a line's counting rule, to print beside its counts."""
    if LineRule(rule) is LineRule.SIDE_CHANGE:
        return "side change within the segment's extent"
    return f"past {hysteresis_m:g} m each side, through the segment"


def _line_rule(value: Any, where: str) -> LineRule | None:
    if value is None:
        return None
    try:
        return LineRule(value)
    except ValueError:
        choices = ", ".join(rule.value for rule in LineRule)
        raise PlaceError(f"{where}: rule must be one of {choices}, got {value!r}.") from None


def _points(value: ArrayLike, what: str, count: int | None = None) -> FloatArray:
    try:
        points = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise PlaceError(f"{what} must be a list of [x, y] points in metres.") from None
    if points.ndim != 2 or points.shape[1] != 2 or (count is not None and len(points) != count):
        expected = f"{count} [x, y] points" if count is not None else "a list of [x, y] points"
        raise PlaceError(f"{what} must be {expected} in metres, got shape {points.shape}.")
    if not np.all(np.isfinite(points)):
        raise PlaceError(f"{what} has a coordinate that is not a finite number.")
    return points


def _segments_cross(p1: FloatArray, p2: FloatArray, q1: FloatArray, q2: FloatArray) -> bool:
    """True when the closed segments p1-p2 and q1-q2 intersect (touching counts)."""

    def orientation(a: FloatArray, b: FloatArray, c: FloatArray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    def on_segment(a: FloatArray, b: FloatArray, c: FloatArray) -> bool:
        return bool(
            min(a[0], b[0]) <= c[0] <= max(a[0], b[0])
            and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])
        )

    d1, d2 = orientation(q1, q2, p1), orientation(q1, q2, p2)
    d3, d4 = orientation(p1, p2, q1), orientation(p1, p2, q2)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0 not in (d1, d2, d3, d4):
        return True
    return (
        (d1 == 0 and on_segment(q1, q2, p1))
        or (d2 == 0 and on_segment(q1, q2, p2))
        or (d3 == 0 and on_segment(p1, p2, q1))
        or (d4 == 0 and on_segment(p1, p2, q2))
    )


@dataclass(frozen=True)
class Zone:
    """A named simple polygon on a plane.

    Attributes:
        name: unique among the site's places.
        polygon: (N, 2) float64 vertices in metres, N >= 3, not closed (the last vertex is not
            repeated), not self-intersecting, non-zero area. Either winding order.
        plane_id: the plane the zone lies on (``None``: every plane).
        hysteresis_m: how far past the border (metres, each side) a track must go to count
            as inside or outside; ``None`` leaves it to the analytics' default.
    """

    name: str
    polygon: FloatArray
    plane_id: int | None = None
    hysteresis_m: float | None = None

    def __post_init__(self) -> None:
        if not self.name:
            raise PlaceError("a zone needs a non-empty name.")
        _check_place_name(self.name, "zone")
        polygon = _points(self.polygon, f"zone {self.name!r}: polygon")
        if len(polygon) >= 2 and np.array_equal(polygon[0], polygon[-1]):
            polygon = polygon[:-1]  # a closed ring written out in full is the same polygon
        if len(polygon) < 3:
            raise PlaceError(f"zone {self.name!r} needs at least 3 vertices, got {len(polygon)}.")
        count = len(polygon)
        for i in range(count):
            for j in range(i + 1, count):
                if j == i + 1 or (i == 0 and j == count - 1):
                    continue  # neighbouring edges share a vertex
                a1, a2 = polygon[i], polygon[(i + 1) % count]
                b1, b2 = polygon[j], polygon[(j + 1) % count]
                if _segments_cross(a1, a2, b1, b2):
                    raise PlaceError(
                        f"zone {self.name!r}: its polygon intersects itself "
                        f"(edge {i + 1} crosses edge {j + 1})."
                    )
        if abs(_shoelace(polygon)) < 1e-9:
            raise PlaceError(f"zone {self.name!r}: its polygon has zero area.")
        _check_hysteresis(self.hysteresis_m, f"zone {self.name!r}")
        polygon.setflags(write=False)
        object.__setattr__(self, "polygon", polygon)

    @property
    def area(self) -> float:
        """Area in square metres."""
        return abs(_shoelace(self.polygon))

    def contains(self, world_xy: ArrayLike) -> BoolArray:
        """Which points lie inside the polygon (even-odd rule; points on an edge may go either way).

        Args:
            world_xy: (N, 2) float64 metres.

        Returns:
            (N,) bool.
        """
        points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
        x, y = points[:, 0:1], points[:, 1:2]
        ax, ay = self.polygon[:, 0], self.polygon[:, 1]
        bx, by = np.roll(ax, -1), np.roll(ay, -1)
        straddles = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = ax + (y - ay) * (bx - ax) / (by - ay)
        inside = np.count_nonzero(straddles & (x < x_cross), axis=1) % 2 == 1
        return inside

    def signed_distance(self, world_xy: ArrayLike) -> FloatArray:
        """Distance to the polygon's border, positive inside, negative outside.

        Args:
            world_xy: (N, 2) float64 metres.

        Returns:
            (N,) float64 metres.
        """
        points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
        x, y = points[:, 0], points[:, 1]
        nearest = np.full(len(points), np.inf)
        # One edge at a time, vectorised over the points: no (N, edges, 2) temporaries.
        for (ax, ay), (bx, by) in zip(self.polygon, np.roll(self.polygon, -1, axis=0),
                                      strict=True):
            ex, ey = bx - ax, by - ay
            fraction = np.clip(((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey), 0.0, 1.0)
            gap_x, gap_y = x - ax - fraction * ex, y - ay - fraction * ey
            np.minimum(nearest, gap_x * gap_x + gap_y * gap_y, out=nearest)
        distance = np.sqrt(nearest)
        return np.where(self.contains(points), distance, -distance)

    def to_dict(self) -> dict[str, Any]:
        """The zone as site-file data (name, polygon, classes)."""
        data: dict[str, Any] = {"name": self.name, "polygon": self.polygon.tolist()}
        if self.plane_id is not None:
            data["plane_id"] = self.plane_id
        if self.hysteresis_m is not None:
            data["hysteresis_m"] = self.hysteresis_m
        return data


def _check_place_name(name: str, what: str) -> None:
    problem = name_problem(name)
    if problem is not None:
        raise PlaceError(f"{what} name {name!r} {problem}.")


def _check_hysteresis(value: Any, what: str) -> None:
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
        np.isfinite(value) and value >= 0
    ):
        raise PlaceError(f"{what}: hysteresis_m must be a number >= 0, got {value!r}.")


def _shoelace(polygon: FloatArray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@dataclass(frozen=True)
class CountingLine:
    """A named counting segment with a positive crossing direction.

    A crossing is movement from the negative to the positive side (``"positive"`` direction)
    or back (``"negative"``), through the segment itself (passing beyond its ends does not
    count). By default the positive side is to the *left* of ``start -> end`` (for a line
    drawn west to east, crossing northwards is positive); ``direction`` overrides it with any
    vector that is not parallel to the line (only which side it points to matters).

    Attributes:
        name: unique among the site's places.
        start, end: (2,) float64 end points, metres, distinct.
        direction: (2,) float64 unit normal pointing to the positive side (derived).
        plane_id: the plane the line lies on (``None``: every plane).
        hysteresis_m: how far past the line (metres, each side) a track must go for a
            crossing to count; ``None`` leaves it to the analytics' default.
        rule: what counts as a crossing (:class:`LineRule`); ``None`` leaves it to the
            analytics' default.
    """

    name: str
    start: FloatArray
    end: FloatArray
    direction: FloatArray | None = None
    plane_id: int | None = None
    hysteresis_m: float | None = None
    rule: LineRule | None = None
    _normal: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.name:
            raise PlaceError("a counting line needs a non-empty name.")
        _check_place_name(self.name, "line")
        start = _points([self.start], f"line {self.name!r}: start", 1)[0]
        end = _points([self.end], f"line {self.name!r}: end", 1)[0]
        along = end - start
        length = float(np.hypot(*along))
        if length < 1e-9:
            raise PlaceError(f"line {self.name!r} has zero length (start and end are the same).")
        left = np.array([-along[1], along[0]]) / length
        if self.direction is None:
            normal = left
        else:
            hint = _points([self.direction], f"line {self.name!r}: direction", 1)[0]
            side = float(np.dot(hint, left))
            if abs(side) < 1e-9 * max(1.0, float(np.hypot(*hint))):
                raise PlaceError(
                    f"line {self.name!r}: direction {hint.tolist()} is parallel to the line; "
                    "give a vector pointing to the positive side."
                )
            normal = left if side > 0 else -left
        _check_hysteresis(self.hysteresis_m, f"line {self.name!r}")
        object.__setattr__(self, "rule", _line_rule(self.rule, f"line {self.name!r}"))
        for array in (start, end, normal):
            array.setflags(write=False)
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "end", end)
        object.__setattr__(self, "direction", normal)
        object.__setattr__(self, "_normal", normal)

    @property
    def length(self) -> float:
        """Length in metres."""
        return float(np.hypot(*(self.end - self.start)))

    def signed_distance(self, world_xy: ArrayLike) -> FloatArray:
        """Distance from the line's infinite extension, positive on the positive side.

        Args:
            world_xy: (N, 2) float64 metres.

        Returns:
            (N,) float64 metres.
        """
        points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
        return (points - self.start) @ self._normal

    def along(self, world_xy: ArrayLike) -> FloatArray:
        """Position along the segment as a fraction: 0 at ``start``, 1 at ``end``.

        Args:
            world_xy: (N, 2) float64 metres.

        Returns:
            (N,) float64 (outside [0, 1] beyond the ends).
        """
        points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
        along = self.end - self.start
        return (points - self.start) @ along / float(along @ along)

    def to_dict(self) -> dict[str, Any]:
        """The line as site-file data (name, end points, directions, classes)."""
        data: dict[str, Any] = {
            "name": self.name,
            "start": self.start.tolist(),
            "end": self.end.tolist(),
            "direction": self.direction.tolist() if self.direction is not None else None,
        }
        if self.plane_id is not None:
            data["plane_id"] = self.plane_id
        if self.hysteresis_m is not None:
            data["hysteresis_m"] = self.hysteresis_m
        if self.rule is not None:
            data["rule"] = self.rule.value
        return data


@dataclass(frozen=True)
class Places:
    """A site's zones and counting lines; names are unique across both."""

    zones: tuple[Zone, ...] = ()
    lines: tuple[CountingLine, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "zones", tuple(self.zones))
        object.__setattr__(self, "lines", tuple(self.lines))
        seen: set[str] = set()
        for name in self.names:
            if name in seen:
                raise PlaceError(f"two places are named {name!r}; names must be unique.")
            seen.add(name)

    def __len__(self) -> int:
        return len(self.zones) + len(self.lines)

    @property
    def names(self) -> list[str]:
        """Every zone's and line's name."""
        return [zone.name for zone in self.zones] + [line.name for line in self.lines]

    def zone(self, name: str) -> Zone:
        """The zone called ``name``; PlaceError naming the known ones otherwise."""
        for zone in self.zones:
            if zone.name == name:
                return zone
        raise PlaceError(f"no zone named {name!r} (zones: {', '.join(self.names) or 'none'}).")

    def line(self, name: str) -> CountingLine:
        """The counting line called ``name``; PlaceError naming the known ones otherwise."""
        for line in self.lines:
            if line.name == name:
                return line
        raise PlaceError(f"no line named {name!r} (lines: {', '.join(self.names) or 'none'}).")

    @classmethod
    def from_iterables(
        cls, zones: Iterable[Zone] = (), lines: Iterable[CountingLine] = ()
    ) -> Places:
        """Places from any iterables of zones and lines."""
        return cls(tuple(zones), tuple(lines))

    def to_dict(self) -> dict[str, list[dict[str, Any]]]:
        """The places as site-file data: ``{"zones": [...], "lines": [...]}``."""
        return {
            "zones": [zone.to_dict() for zone in self.zones],
            "lines": [line.to_dict() for line in self.lines],
        }

    @classmethod
    def from_dict(cls, data: Any) -> Places:
        """Places from ``{"zones": [...], "lines": [...]}`` as :meth:`to_dict` writes them.

        This is the ``places:`` section of a site file. Unknown keys are errors naming their path.
        """
        if not isinstance(data, dict):
            raise PlaceError("places must be a mapping with 'zones' and/or 'lines'.")
        _no_unknown(data, {"zones", "lines"}, "places")
        zones, lines = data.get("zones") or [], data.get("lines") or []
        if not isinstance(zones, list) or not isinstance(lines, list):
            raise PlaceError("places.zones and places.lines must be lists.")
        zone_keys, line_keys = {"name", "polygon", "plane_id", "hysteresis_m"}, set(_LINE_KEYS)
        built_zones = []
        for index, item in enumerate(zones):
            where = f"places.zones[{index}]"
            if not isinstance(item, dict):
                raise PlaceError(f"{where} must be a mapping with name and polygon.")
            _no_unknown(item, zone_keys, where)
            if "polygon" not in item:
                raise PlaceError(f"{where} ({item.get('name', 'unnamed')}) has no polygon.")
            built_zones.append(
                Zone(
                    str(item.get("name", "")),
                    item["polygon"],
                    item.get("plane_id"),
                    hysteresis_m=item.get("hysteresis_m"),
                )
            )
        built_lines = []
        for index, item in enumerate(lines):
            where = f"places.lines[{index}]"
            if not isinstance(item, dict):
                raise PlaceError(f"{where} must be a mapping with name, start and end.")
            _no_unknown(item, line_keys, where)
            missing = [key for key in ("start", "end") if key not in item]
            if missing:
                raise PlaceError(
                    f"{where} ({item.get('name', 'unnamed')}) has no {' or '.join(missing)}."
                )
            built_lines.append(
                CountingLine(
                    str(item.get("name", "")),
                    item["start"],
                    item["end"],
                    direction=item.get("direction"),
                    plane_id=item.get("plane_id"),
                    hysteresis_m=item.get("hysteresis_m"),
                    rule=_line_rule(item.get("rule"), where),
                )
            )
        return cls(tuple(built_zones), tuple(built_lines))


_LINE_KEYS = ("name", "start", "end", "direction", "plane_id", "hysteresis_m", "rule")


def _no_unknown(mapping: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(mapping) - allowed)
    if unknown:
        raise PlaceError(
            f"{where}.{unknown[0]}: unknown key (allowed: {', '.join(sorted(allowed))})."
        )


def bounding_box(places: Places) -> tuple[float, float, float, float] | None:
    """(x_min, y_min, x_max, y_max) in metres over every place, or ``None`` without places."""
    arrays = [zone.polygon for zone in places.zones]
    arrays += [np.stack([line.start, line.end]) for line in places.lines]
    if not arrays:
        return None
    points = np.concatenate(arrays)
    return (
        float(points[:, 0].min()),
        float(points[:, 1].min()),
        float(points[:, 0].max()),
        float(points[:, 1].max()),
    )
