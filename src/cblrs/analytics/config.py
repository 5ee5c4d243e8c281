"""Settings of the analytics and the events they produce."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

from cblrs.errors import CblrsError
from cblrs.localtime import LocalCalendar, LocalTimeError
from cblrs.places import LineRule


class AnalyticsError(CblrsError):
    """Analytics cannot run on this input (no places, tracks from another site, bad settings)."""


@dataclass(frozen=True)
class HeatmapGrid:
    """A metric grid on the ground plane for the occupancy heatmap.

    Attributes:
        origin: (x, y) metres of the grid's lower-left corner.
        size: (width, length) metres; rounded up to whole cells.
        cell_m: side of a square cell, metres.
    """

    origin: tuple[float, float]
    size: tuple[float, float]
    cell_m: float = 0.5

    def __post_init__(self) -> None:
        values = (*self.origin, *self.size, self.cell_m)
        if not all(math.isfinite(value) for value in values):
            raise AnalyticsError("the heatmap grid needs finite numbers.")
        if not (self.cell_m > 0 and self.size[0] > 0 and self.size[1] > 0):
            raise AnalyticsError(
                f"the heatmap grid needs a positive size and cell, got size {self.size}, "
                f"cell {self.cell_m} m."
            )
        if self.shape[0] * self.shape[1] > 25_000_000:
            raise AnalyticsError(
                f"a heatmap of {self.shape[1]} x {self.shape[0]} cells is too large; "
                "use a larger cell."
            )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, columns along x)."""
        return (
            max(1, math.ceil(self.size[1] / self.cell_m - 1e-9)),
            max(1, math.ceil(self.size[0] / self.cell_m - 1e-9)),
        )

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) metres of the whole grid (for ``imshow``)."""
        rows, columns = self.shape
        x0, y0 = self.origin
        return (x0, x0 + columns * self.cell_m, y0, y0 + rows * self.cell_m)

    @classmethod
    def covering(
        cls, bounds: tuple[float, float, float, float], cell_m: float = 0.5
    ) -> HeatmapGrid:
        """The grid of ``cell_m`` cells, aligned to multiples of the cell, covering
        ``(x_min, y_min, x_max, y_max)``."""
        x_min, y_min, x_max, y_max = bounds
        x0 = math.floor(x_min / cell_m) * cell_m
        y0 = math.floor(y_min / cell_m) * cell_m
        x1 = max(math.ceil(x_max / cell_m) * cell_m, x0 + cell_m)
        y1 = max(math.ceil(y_max / cell_m) * cell_m, y0 + cell_m)
        return cls((x0, y0), (x1 - x0, y1 - y0), cell_m)

    def to_dict(self) -> dict[str, Any]:
        return {"origin": list(self.origin), "size": list(self.size), "cell_m": self.cell_m}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HeatmapGrid:
        origin, size = data["origin"], data["size"]
        return cls((float(origin[0]), float(origin[1])), (float(size[0]), float(size[1])),
                   float(data["cell_m"]))


@dataclass(frozen=True)
class AnalyticsConfig:
    """How tracks are turned into counts. Defaults suit people tracked at 2-30 Hz.

    Attributes:
        line_hysteresis_m: a crossing counts when a track goes from farther than this on one
            side of a line to farther than this on the other, through the segment (a line's
            own ``hysteresis_m`` overrides it). Jitter across the line counts nothing.
        line_rule: ``"hysteresis"`` (the rule above, the default) or ``"side_change"``
            (common tools' rule: any change of side between positions within the
            segment's extent; :class:`cblrs.places.LineRule`); a line's own ``rule`` wins.
        zone_hysteresis_m: a track is inside a zone once it is this far inside the border,
            and outside once this far outside (a zone's own ``hysteresis_m`` overrides it).
            Entry and exit times are taken where the track crossed the border itself, so
            dwell times are not biased by the margin.
        merge_gap_s: a track that leaves a zone and comes back within this many seconds
            continues its visit (no extra entry, exit or visit): an id flickering at the
            border makes one visit. ``zone_left`` is reported only once this has passed.
        lost_after_s: a track not seen for longer than this has ended (its open visits end
            where it was last seen); if its id comes back, that is a new life, and nothing is
            counted across the unobserved gap.
        max_person_speed_m_s, max_speed_m_s: a step between consecutive rows faster than
            this (people; other and unknown classes) is not movement but a jump — an
            identity switch or an annotation error — and ends the track's life there, so no
            crossing is counted along a straight line the object never walked.
        min_track_s: a track's events count only once it has lived this long (first to
            latest row of its life); shorter-lived ids (false positives, id fragments)
            count nothing. Until then its events are held, then released with their times.
        interval_s: width of the time bins of the counts-over-time tables, seconds; bins are
            aligned to multiples of it from time 0, so the same tracks always bin alike.
            With a ``timezone`` they are aligned to the local clock instead (an hour bin
            starts at local hh:00, a day bin at local midnight; the width must divide a day).
        heatmap: the heatmap grid; None: no heatmap.
        timezone: IANA zone of the times (epoch seconds), e.g. ``"Europe/Zurich"``; None:
            bins from time 0 (UTC for epoch seconds).
        opening_hours: the site's opening hours (:class:`cblrs.localtime.OpeningHours`
            mapping, e.g. ``{"mon-fri": "07:00-19:00"}``; needs ``timezone``): only events
            at open times count — a crossing at its crossing instant, an entry at its entry
            instant, a visit (dwell, exit, occupancy, OD) by when it began, in full even if
            it ends after closing. Ranges are half-open: a crossing at 19:00:00 of
            ``07:00-19:00`` does not count. None: always open.
    """

    line_hysteresis_m: float = 0.5
    line_rule: str = LineRule.HYSTERESIS.value
    zone_hysteresis_m: float = 0.5
    merge_gap_s: float = 2.0
    lost_after_s: float = 2.0
    max_person_speed_m_s: float = 10.0
    max_speed_m_s: float = 70.0
    min_track_s: float = 1.0
    interval_s: float = 60.0
    heatmap: HeatmapGrid | None = None
    timezone: str | None = None
    opening_hours: dict[str, str] | None = None

    def __post_init__(self) -> None:
        try:
            calendar = LocalCalendar.of(self.timezone, self.opening_hours)
            if calendar is not None:
                calendar.check_interval(self.interval_s)
        except LocalTimeError as error:
            raise AnalyticsError(f"{str(error).rstrip('.')}.") from None
        if calendar is not None and calendar.opening_hours is not None:
            # One spelling of the same hours, so that saved states compare equal.
            object.__setattr__(self, "opening_hours", calendar.opening_hours.to_dict())
        object.__setattr__(self, "_calendar", calendar)
        if self.line_rule not in {rule.value for rule in LineRule}:
            choices = ", ".join(rule.value for rule in LineRule)
            raise AnalyticsError(f"line_rule must be one of {choices}, got {self.line_rule!r}.")
        for name in ("line_hysteresis_m", "zone_hysteresis_m", "merge_gap_s", "min_track_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise AnalyticsError(f"{name} must be a number >= 0, got {value}.")
        for name in ("lost_after_s", "interval_s", "max_person_speed_m_s", "max_speed_m_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise AnalyticsError(f"{name} must be a positive number, got {value}.")

    @property
    def calendar(self) -> LocalCalendar | None:
        """The time zone and opening hours (None without a ``timezone``)."""
        return self._calendar  # type: ignore[attr-defined]

    def time_bins(self) -> TimeBins:
        """The counts-over-time bins of these settings."""
        return TimeBins(self.interval_s, self.calendar)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["heatmap"] = None if self.heatmap is None else self.heatmap.to_dict()
        return data

    def line_rules(self, places: Any) -> list[tuple[LineRule, float]]:
        """Each counting line's rule and hysteresis (its own settings, else these)."""
        return [
            (
                LineRule(line.rule or self.line_rule),
                self.line_hysteresis_m if line.hysteresis_m is None else line.hysteresis_m,
            )
            for line in places.lines
        ]

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AnalyticsConfig:
        values = dict(data)
        grid = values.pop("heatmap", None)
        return cls(**values, heatmap=None if grid is None else HeatmapGrid.from_dict(grid))


class TimeBins:
    """Time bins keyed by an integer: ``floor(t / interval_s)`` from time 0, or with a
    calendar the bin's start in whole epoch seconds (local bins differ in length)."""

    def __init__(self, interval_s: float, calendar: LocalCalendar | None = None):
        self.interval_s = float(interval_s)
        self.calendar = calendar
        self._last: tuple[float, float] = (math.inf, -math.inf)

    def key(self, timestamp: float) -> int:
        """The key of the bin holding ``timestamp``."""
        if self.calendar is None:
            return math.floor(timestamp / self.interval_s)
        start, end = self._last
        if not start <= timestamp < end:
            start = self.calendar.bin_start(timestamp, self.interval_s)
            end = self.calendar.bin_end(start, self.interval_s)
            self._last = (start, end)
        return round(start)

    def start(self, key: int) -> float:
        """Start of a bin, seconds."""
        return float(key) if self.calendar is not None else key * self.interval_s

    def end(self, key: int) -> float:
        """End of a bin (the next one's start), seconds."""
        if self.calendar is None:
            return (key + 1) * self.interval_s
        return self.calendar.bin_end(float(key), self.interval_s)

    def following(self, key: int) -> int:
        """The key of the next bin."""
        return key + 1 if self.calendar is None else round(self.end(key))


@dataclass(frozen=True)
class LineCrossing:
    """A track crossed a counting line (``line_crossed``).

    Attributes:
        line: the line's name.
        track_id: the global track id.
        timestamp: when it crossed the line itself (interpolated), seconds.
        direction: ``"positive"`` or ``"negative"``.
        class_id: the track's class at that moment (-1 unknown).
        world_xy: where it crossed, metres.
    """

    line: str
    track_id: int
    timestamp: float
    direction: str
    class_id: int
    world_xy: tuple[float, float]

    kind = "line_crossed"


@dataclass(frozen=True)
class ZoneEntered:
    """A visit began (``zone_entered``).

    Attributes:
        zone: the zone's name.
        track_id: the global track id.
        timestamp: when the visit began (border crossing, interpolated), seconds.
        crossed: True when the track was seen outside first (an entry); False when it was
            first seen already inside (appeared, e.g. at the edge of coverage).
        class_id: the track's class (-1 unknown).
    """

    zone: str
    track_id: int
    timestamp: float
    crossed: bool
    class_id: int

    kind = "zone_entered"


@dataclass(frozen=True)
class ZoneLeft:
    """A visit ended (``zone_left``), reported once it can no longer continue.

    Attributes:
        zone, track_id, class_id: as in :class:`ZoneEntered`.
        entered_at: when the visit began, seconds.
        timestamp: when it ended (border crossing, or last seen when the track was lost).
        dwell_s: ``timestamp - entered_at``.
        entered: the visit began with an entry (not an appearance inside).
        exited: it ended with an exit (not by the track being lost or the data ending).
    """

    zone: str
    track_id: int
    entered_at: float
    timestamp: float
    dwell_s: float
    entered: bool
    exited: bool
    class_id: int

    kind = "zone_left"


Event = LineCrossing | ZoneEntered | ZoneLeft


def event_to_dict(event: Event) -> dict[str, Any]:
    """An event as a JSON-ready dict with its ``kind`` (e.g. for a message payload)."""
    data = asdict(event)
    data["kind"] = event.kind
    return data


def event_from_dict(data: dict[str, Any]) -> Event:
    """The event of :func:`event_to_dict`."""
    values = dict(data)
    kind = values.pop("kind")
    if kind == LineCrossing.kind:
        values["world_xy"] = tuple(values["world_xy"])
        return LineCrossing(**values)
    if kind == ZoneEntered.kind:
        return ZoneEntered(**values)
    return ZoneLeft(**values)


def json_round_trip(data: Any) -> Any:
    """What ``data`` looks like after a JSON round trip (tuples become lists)."""
    return json.loads(json.dumps(data))
