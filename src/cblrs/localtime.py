"""A site's local time: its IANA time zone, opening hours and time bins on the local clock.

Times in cblrs are epoch seconds (the runtime's capture times; offline scenes add the time of
their second 0). :class:`LocalCalendar` turns them into what people on site read: local ISO
times with their offset (``2026-03-29T03:00:00+02:00``), whether the site is open, and time
bins that start on the local clock (an hour bin at hh:00, a day bin at local midnight). On a
daylight-saving change the local day has 23 or 25 hours, so it has 23 or 25 hour bins; the
repeated hour of the autumn change is two bins, told apart by their offset.

Opening hours are wall-clock ranges per weekday, half-open (``07:00-19:00`` is open from
07:00:00 up to, not including, 19:00:00)::

    timezone: Europe/Zurich
    opening_hours:
      mon-fri: "07:00-19:00"
      sat: "09:00-12:00, 13:00-17:00"
      sun: closed                  # days left out are closed too
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from datetime import datetime
from itertools import pairwise
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from cblrs.errors import CblrsError

WEEKDAYS = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
DAY_S = 86400
_RANGE = re.compile(r"^(\d{1,2}):(\d{2})\s*-\s*(\d{1,2}):(\d{2})$")


class LocalTimeError(CblrsError):
    """A time zone, opening hours or local time bin that cannot be used."""


def time_zone(name: Any) -> ZoneInfo:
    """The IANA zone ``name`` (e.g. ``Europe/Zurich``); one sentence when there is none."""
    if not isinstance(name, str) or not name.strip():
        raise LocalTimeError("timezone must be an IANA name such as Europe/Zurich or UTC")
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise LocalTimeError(
            f"unknown time zone {name!r}: give an IANA name such as Europe/Zurich, "
            "America/New_York or UTC"
        ) from None


def _day_keys(key: Any) -> list[int]:
    if not isinstance(key, str):
        raise LocalTimeError(f"opening_hours: {key!r} is not a day (mon ... sun, or mon-fri)")
    days: list[int] = []
    for part in key.lower().replace(" ", "").split(","):
        first, _, last = part.partition("-")
        if first not in WEEKDAYS or (last and last not in WEEKDAYS):
            raise LocalTimeError(
                f"opening_hours: {key!r} is not a day or range of days (mon ... sun, "
                "mon-fri, sat,sun)"
            )
        start, stop = WEEKDAYS.index(first), WEEKDAYS.index(last or first)
        if stop < start:
            raise LocalTimeError(f"opening_hours: {key!r} runs backwards (write e.g. mon-fri)")
        days += range(start, stop + 1)
    return days


def _ranges(key: str, value: Any) -> tuple[tuple[int, int], ...]:
    if value is None or value is False or (isinstance(value, str)
                                           and value.strip().lower() == "closed"):
        return ()
    items = value.split(",") if isinstance(value, str) else value
    if not isinstance(items, list | tuple):
        raise LocalTimeError(f"opening_hours: {key}: expected \"HH:MM-HH:MM\" or closed")
    ranges = []
    for item in items:
        match = _RANGE.match(str(item).strip()) if isinstance(item, str) else None
        if match is None:
            raise LocalTimeError(
                f"opening_hours: {key}: {item!r} is not a range \"HH:MM-HH:MM\" (or closed)"
            )
        h0, m0, h1, m1 = (int(group) for group in match.groups())
        start, end = h0 * 3600 + m0 * 60, h1 * 3600 + m1 * 60
        if m0 > 59 or m1 > 59 or start >= DAY_S or end > DAY_S:
            raise LocalTimeError(f"opening_hours: {key}: {item!r} is not a time of day "
                                 "(00:00 to 24:00)")
        if end <= start:
            raise LocalTimeError(
                f"opening_hours: {key}: {item!r} ends before it starts; split a range past "
                "midnight over two days (fri: 22:00-24:00, sat: 00:00-02:00)"
            )
        ranges.append((start, end))
    ranges.sort()
    for (_, end), (start, _) in pairwise(ranges):
        if start < end:
            raise LocalTimeError(f"opening_hours: {key}: ranges overlap")
    return tuple(ranges)


def _text(seconds: int) -> str:
    return f"{seconds // 3600:02d}:{seconds % 3600 // 60:02d}"


@dataclass(frozen=True)
class OpeningHours:
    """Per weekday (Monday first) the open ranges, seconds of the local wall-clock day."""

    days: tuple[tuple[tuple[int, int], ...], ...]

    @classmethod
    def parse(cls, data: Any) -> OpeningHours:
        """From the site file's mapping (``mon-fri: "07:00-19:00"``, ``sun: closed``).

        Raises:
            LocalTimeError: a bad day, range or a day given twice (one sentence).
        """
        if isinstance(data, OpeningHours):
            return data
        if not isinstance(data, dict) or not data:
            raise LocalTimeError(
                "opening_hours must map days to ranges, e.g. mon-fri: \"07:00-19:00\""
            )
        days: list[tuple[tuple[int, int], ...] | None] = [None] * 7
        for key, value in data.items():
            ranges = _ranges(str(key), value)
            for day in _day_keys(key):
                if days[day] is not None:
                    raise LocalTimeError(f"opening_hours: {WEEKDAYS[day]} is given twice")
                days[day] = ranges
        return cls(tuple(day or () for day in days))

    def to_dict(self) -> dict[str, str]:
        """Every weekday's ranges as text (``"closed"`` for none); :meth:`parse` reads it."""
        return {
            name: ", ".join(f"{_text(a)}-{_text(b)}" for a, b in ranges) or "closed"
            for name, ranges in zip(WEEKDAYS, self.days, strict=True)
        }

    def open_at(self, local: datetime) -> bool:
        """Whether a local (aware or wall-clock) time is within the hours."""
        second = local.hour * 3600 + local.minute * 60 + local.second + local.microsecond / 1e6
        return any(start <= second < end for start, end in self.days[local.weekday()])


@dataclass(frozen=True)
class LocalCalendar:
    """A site's time zone and opening hours (None: always open), on epoch seconds.

    Example:
        >>> calendar = LocalCalendar("Europe/Zurich")
        >>> calendar.iso(1774746000.0)
        '2026-03-29T03:00:00+02:00'
        >>> (calendar.bin_end(1774738800.0, 86400) - 1774738800.0) / 3600  # 2026-03-29: 23 h
        23.0
    """

    timezone: str
    opening_hours: OpeningHours | None = None
    zone: ZoneInfo = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "zone", time_zone(self.timezone))

    @classmethod
    def of(cls, timezone: str | None, opening_hours: Any = None) -> LocalCalendar | None:
        """The calendar of a site's ``timezone`` and ``opening_hours`` (None without a zone).

        Raises:
            LocalTimeError: a bad zone or hours, or hours without a zone.
        """
        if timezone is None:
            if opening_hours is not None:
                raise LocalTimeError(
                    "opening_hours need the site's timezone (e.g. timezone: Europe/Zurich)"
                )
            return None
        hours = None if opening_hours is None else OpeningHours.parse(opening_hours)
        return cls(timezone, hours)

    # ------------------------------------------------------------------ reading times
    def local(self, timestamp: float) -> datetime:
        """The aware local time of epoch seconds."""
        return datetime.fromtimestamp(timestamp, self.zone)

    def iso(self, timestamp: float) -> str:
        """Local ISO 8601 time with its offset; milliseconds only when not whole seconds."""
        whole = abs(timestamp - round(timestamp)) < 5e-4
        return self.local(round(timestamp) if whole else timestamp).isoformat(
            timespec="seconds" if whole else "milliseconds")

    def is_open(self, timestamp: float) -> bool:
        """Whether the site is open at epoch seconds ``timestamp`` (no hours: always)."""
        if self.opening_hours is None:
            return True
        return self.opening_hours.open_at(self.local(timestamp))

    # ------------------------------------------------------------------ bins
    @staticmethod
    def check_interval(interval_s: float) -> None:
        """Local bins need a width that divides a day (1 s ... 1 h ... 1 day).

        Raises:
            LocalTimeError: it does not.
        """
        if not (math.isfinite(interval_s) and interval_s >= 1 and interval_s == int(interval_s)
                and DAY_S % int(interval_s) == 0):
            raise LocalTimeError(
                f"with a time zone the bin width must divide a day (e.g. 60, 900, 3600 or "
                f"86400 s), got {interval_s:g} s"
            )

    def offset(self, timestamp: float) -> int:
        """The zone's UTC offset at epoch seconds ``timestamp``, seconds."""
        delta = self.local(timestamp).utcoffset()
        return 0 if delta is None else round(delta.total_seconds())

    def _transition(self, before: float, after: float) -> int:
        """The first whole second in (before, after] with ``after``'s offset (zones change
        offset on whole seconds; one change in between)."""
        low, high, target = math.floor(before), math.floor(after), self.offset(after)
        while high - low > 1:
            middle = (low + high) // 2
            if self.offset(middle) == target:
                high = middle
            else:
                low = middle
        return high

    def bin_start(self, timestamp: float, interval_s: float) -> float:
        """Start (epoch seconds) of the local bin holding ``timestamp``.

        Bins start where the local wall clock shows a multiple of ``interval_s`` (hh:00 for
        hours, midnight for days); a repeated hour gives its multiples twice (two bins), and
        a multiple the clock skips moves to the instant of the change (a 02:00 bin skipped
        in spring starts at 03:00).
        """
        width = int(interval_s)
        moment = timestamp
        for _ in range(8):
            offset = self.offset(moment)
            start = math.floor((moment + offset) / width) * width - offset
            if self.offset(start) == offset:
                return float(start)
            change = self._transition(start, moment)
            if start + offset > change - 1 + self.offset(change - 1):
                return float(change)  # the boundary fell in a skipped stretch of the clock
            moment = change - 1  # the bin began before the change, on the old offset
        raise LocalTimeError(f"no local bin boundary found before {timestamp}")  # pragma: no cover

    def bin_end(self, start: float, interval_s: float) -> float:
        """The next bin's start after a bin starting at ``start`` (epoch seconds)."""
        width = int(interval_s)
        offset = self.offset(start)
        end = math.floor((start + offset) / width) * width + width - offset
        if self.offset(end) == offset:
            return float(end)
        change = self._transition(start, end)
        after = self.offset(change)
        if math.floor((change + after) / width) * width > change - 1 + offset:
            return float(change)  # the clock jumped to or over a boundary at the change
        return float(math.ceil((change + after) / width) * width - after)


def parse_time(text: str, calendar: LocalCalendar | None = None) -> float:
    """Epoch seconds of a number or an ISO time (without offset: in ``calendar``'s zone, or
    UTC without one).

    Raises:
        LocalTimeError: neither.
    """
    try:
        return float(text)
    except ValueError:
        pass
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        raise LocalTimeError(
            f"{text!r} is neither epoch seconds nor an ISO time (e.g. 2026-03-29T08:00:00)"
        ) from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=calendar.zone if calendar else ZoneInfo("UTC"))
    return moment.timestamp()
