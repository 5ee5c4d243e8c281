"""Offline analytics: feed a whole :class:`Tracks` to the engine and read its tables.

:func:`analyse_tracks` is the engine (:class:`cblrs.analytics.Analytics`) fed in time-ordered
chunks and flushed; :class:`AnalyticsResult` holds plain tables (lists of dicts, numpy for the
heatmap) that :func:`write_result` saves as CSV and JSON.
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from cblrs.analytics.config import AnalyticsConfig, Event, LineCrossing, ZoneLeft
from cblrs.analytics.engine import Analytics
from cblrs.detections import CLASS_NAMES, Tracks
from cblrs.localtime import LocalCalendar
from cblrs.places import Places, line_rule_text

DIRECTIONS = ("positive", "negative")


def class_name(class_id: int) -> str:
    """``"person"`` for 0 ..., ``"unknown"`` for -1 (or an id outside :data:`CLASS_NAMES`)."""
    return CLASS_NAMES[class_id] if 0 <= class_id < len(CLASS_NAMES) else "unknown"


@dataclass(frozen=True, eq=False)
class AnalyticsResult:
    """Every table of one analytics run.

    Attributes:
        lines: per line, direction and class: ``{line, direction, class, count, rule}``
            (every line and direction appears, with class ``"all"`` summing the classes;
            ``rule`` says what counted as a crossing, :func:`cblrs.places.line_rule_text`).
        zones: per zone: entries (crossed in), appeared (first seen inside), exits, visits,
            mean / median dwell of all visits and mean dwell of complete visits (entered and
            exited), person-seconds inside.
        counts_over_time: ``{bin_start_s, place, kind, class, count}``; kind is a direction
            for lines, ``entries`` / ``exits`` for zones. With a time zone
            (``AnalyticsConfig.timezone``) each row also has ``bin_start``, the local ISO
            time with its offset, and ``bin_s``, the bin's length (23 h for the day of the
            spring change, 25 h in autumn).
        occupancy: ``{bin_start_s, zone, mean_occupancy}`` (and ``bin_start``, ``bin_s``
            with a time zone): person-seconds in the bin / bin length.
        od: ``{origin: {destination: count}}`` over zones, for lives with two or more visits.
        od_unpaired: per zone, lives with a single visit (origin or destination unknown).
        crossings: every counted crossing, in time order.
        visits: every visit, in order of its start.
        heatmap: (rows, columns) float64 person-seconds per cell (row 0 at the grid's
            lowest y), or None.
        summary: rows, late rows, events outside opening hours, time span, settings.
        calendar: the time zone and opening hours the times were read in (None: none).
    """

    lines: list[dict[str, Any]]
    zones: list[dict[str, Any]]
    counts_over_time: list[dict[str, Any]]
    occupancy: list[dict[str, Any]]
    od: dict[str, dict[str, int]]
    od_unpaired: dict[str, int]
    crossings: list[LineCrossing]
    visits: list[ZoneLeft]
    heatmap: NDArray[np.float64] | None
    summary: dict[str, Any] = field(default_factory=dict)
    calendar: LocalCalendar | None = None

    def line_count(self, line: str, direction: str, class_label: str = "all") -> int:
        for row in self.lines:
            if (row["line"], row["direction"], row["class"]) == (line, direction, class_label):
                return int(row["count"])
        return 0

    def zone_row(self, zone: str) -> dict[str, Any]:
        for row in self.zones:
            if row["zone"] == zone:
                return row
        raise KeyError(zone)

    def to_json(self) -> dict[str, Any]:
        """Everything but the event lists and heatmap cells, as plain JSON."""
        return {
            "summary": self.summary,
            "lines": self.lines,
            "zones": self.zones,
            "od": self.od,
            "od_unpaired": self.od_unpaired,
            "counts_over_time": self.counts_over_time,
            "occupancy": self.occupancy,
        }


def analyse_tracks(
    tracks: Tracks,
    places: Places,
    config: AnalyticsConfig | None = None,
    chunk_rows: int = 100_000,
) -> AnalyticsResult:
    """Run the analytics over a whole set of tracks (offline).

    Args:
        tracks: any row order; sorted by time here. Timestamps in seconds.
        places: the site's zones and lines (at least one).
        config: settings; defaults suit people.
        chunk_rows: rows per engine update (bounds memory; the result does not depend on it).

    Returns:
        The tables; identical to an :class:`Analytics` fed the same rows update by update.

    Example:
        >>> from cblrs.places import CountingLine
        >>> places = Places(lines=(CountingLine("gate", (0, -5), (0, 5)),))
        >>> walk = Tracks(np.arange(6), np.arange(6.0), np.ones(6, int),
        ...               np.c_[np.linspace(-3, 3, 6), np.zeros(6)])
        >>> analyse_tracks(walk, places).line_count("gate", "negative")
        1
    """
    engine = Analytics(places, config)
    order = np.argsort(tracks.timestamp, kind="stable")
    ordered = tracks[order]
    times = ordered.timestamp
    events: list[Event] = []
    start = 0
    while start < len(ordered):
        stop = min(start + max(chunk_rows, 1), len(ordered))
        # Never split one instant between two updates.
        stop = int(np.searchsorted(times, times[stop - 1], side="right"))
        events += engine.update(ordered[start:stop])
        start = stop
    events += engine.flush()
    return result_of(engine, events)


def result_of(engine: Analytics, events: list[Event]) -> AnalyticsResult:
    """The tables of a flushed engine (``events``: all it emitted, for the event lists)."""
    places, config = engine.places, engine.config
    classes = sorted({key[2] for key in engine.line_counts})
    lines = []
    for line, (rule, band) in zip(places.lines, config.line_rules(places), strict=True):
        # Which rule made the count goes beside it: rules differ by ~10 % on real tracks.
        text = line_rule_text(rule, band)
        for direction in DIRECTIONS:
            total = 0
            for class_id in classes:
                count = engine.line_counts.get((line.name, direction, class_id), 0)
                total += count
                if count:
                    lines.append({"line": line.name, "direction": direction,
                                  "class": class_name(class_id), "count": count,
                                  "rule": text})
            lines.append({"line": line.name, "direction": direction, "class": "all",
                          "count": total, "rule": text})
    visits_by_zone: dict[str, list[ZoneLeft]] = {zone.name: [] for zone in places.zones}
    for visit in engine.visits:
        visits_by_zone[visit.zone].append(visit)
    zones = []
    for zone in places.zones:
        visits = visits_by_zone[zone.name]
        dwell = np.array([visit.dwell_s for visit in visits])
        complete = np.array([v.dwell_s for v in visits if v.entered and v.exited])
        zones.append({
            "zone": zone.name,
            "entries": sum(v for (name, _), v in engine.zone_entries.items() if name == zone.name),
            "appeared": sum(
                v for (name, _), v in engine.zone_appeared.items() if name == zone.name
            ),
            "exits": sum(1 for visit in visits if visit.exited),
            "visits": len(visits),
            "mean_dwell_s": _mean(dwell),
            "median_dwell_s": float(np.median(dwell)) if len(dwell) else math.nan,
            "complete_visits": len(complete),
            "mean_dwell_complete_s": _mean(complete),
            "person_seconds": float(dwell.sum()),
        })
    bins, calendar = engine.bins, config.calendar

    def when(bin_index: int) -> dict[str, Any]:
        start = bins.start(bin_index)
        if calendar is None:
            return {"bin_start_s": start}
        # Local bins differ in length (a day of 23 or 25 hours): the end goes beside.
        return {"bin_start_s": start, "bin_start": calendar.iso(start),
                "bin_s": bins.end(bin_index) - start}

    counts_over_time = [
        {**when(bin_index), "place": line, "kind": direction,
         "class": class_name(class_id), "count": count}
        for (bin_index, line, direction, class_id), count in engine.line_bins.items()
    ] + [
        {**when(bin_index), "place": zone, "kind": kind, "class": "all", "count": count}
        for (bin_index, zone, kind), count in engine.zone_bins.items()
    ]
    counts_over_time.sort(key=lambda row: (row["bin_start_s"], row["place"], row["kind"],
                                           row["class"]))
    occupancy = [
        {**when(bin_index), "zone": zone,
         "mean_occupancy": seconds / (bins.end(bin_index) - bins.start(bin_index))}
        for (bin_index, zone), seconds in sorted(engine.occupancy_seconds.items())
    ]
    names = [zone.name for zone in places.zones]
    od = {origin: {destination: engine.od.get((origin, destination), 0) for destination in names}
          for origin in names}
    crossings = sorted((e for e in events if isinstance(e, LineCrossing)),
                       key=lambda e: (e.timestamp, e.track_id, e.line))
    visits = sorted(engine.visits, key=lambda e: (e.entered_at, e.track_id, e.zone))
    summary = {
        "rows": engine.rows,
        "late_rows": engine.late_rows,
        "closed_events": engine.closed_events,
        "end_s": None if math.isinf(engine.clock) else engine.clock,
        "settings": config.to_dict(),
        "heatmap_outside_person_seconds": engine.heatmap_outside_s,
    }
    return AnalyticsResult(
        lines=lines, zones=zones, counts_over_time=counts_over_time, occupancy=occupancy,
        od=od, od_unpaired={name: engine.od_unpaired.get(name, 0) for name in names},
        crossings=crossings, visits=visits,
        heatmap=engine.heatmap.copy() if config.heatmap is not None else None,
        summary=summary, calendar=calendar,
    )


def _mean(values: NDArray[np.float64]) -> float:
    return float(values.mean()) if len(values) else math.nan


def write_result(result: AnalyticsResult, out: str | Path) -> list[Path]:
    """Write the tables as CSV files and ``analytics.json`` into ``out``; returns the paths.

    The files describe people's movements (each crossing's track, time and position), so
    they are written readable by their owner only (0600; a new ``out`` folder 0700).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True, mode=0o700)
    written = []

    def table(name: str, rows: list[dict[str, Any]], columns: list[str]) -> None:
        path = out / name
        with open_private(path, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            for row in rows:
                writer.writerow({key: _cell(row[key]) for key in columns})
        written.append(path)

    table("lines.csv", result.lines, ["line", "direction", "class", "count", "rule"])
    table("zones.csv", result.zones, list(result.zones[0]) if result.zones else ["zone"])
    calendar = result.calendar
    local = ["bin_start", "bin_s"] if calendar is not None else []
    table("counts_over_time.csv", result.counts_over_time,
          ["bin_start_s", *local, "place", "kind", "class", "count"])
    table("occupancy.csv", result.occupancy, ["bin_start_s", *local, "zone", "mean_occupancy"])

    names = list(result.od)
    table("od.csv",
          [{"origin": origin, **result.od[origin], "unpaired": result.od_unpaired[origin]}
           for origin in names],
          ["origin", *names, "unpaired"])
    table("crossings.csv",
          [{"timestamp_s": e.timestamp, **_local("time", e.timestamp, calendar),
            "line": e.line, "track_id": e.track_id,
            "direction": e.direction, "class": class_name(e.class_id),
            "x_m": e.world_xy[0], "y_m": e.world_xy[1]} for e in result.crossings],
          ["timestamp_s", *(["time"] if calendar else []), "line", "track_id", "direction",
           "class", "x_m", "y_m"])
    table("visits.csv",
          [{"zone": e.zone, "track_id": e.track_id, "class": class_name(e.class_id),
            "start_s": e.entered_at, **_local("start", e.entered_at, calendar),
            "end_s": e.timestamp, **_local("end", e.timestamp, calendar),
            "dwell_s": e.dwell_s, "entered": e.entered, "exited": e.exited}
           for e in result.visits],
          ["zone", "track_id", "class", "start_s", *(["start"] if calendar else []), "end_s",
           *(["end"] if calendar else []), "dwell_s", "entered", "exited"])
    if result.heatmap is not None:
        path = out / "heatmap.csv"
        with open_private(path, "w") as handle:
            np.savetxt(handle, result.heatmap, delimiter=",", fmt="%.4g",
                       header="person-seconds per cell; row 0 = lowest y (see "
                       "analytics.json)")
        written.append(path)
    path = out / "analytics.json"
    with open_private(path, "w") as handle:
        handle.write(json.dumps(json_safe(result.to_json()), indent=1) + "\n")
    written.append(path)
    return written


def open_private(path: Path, mode: str, **options: Any) -> IO[Any]:
    """Open ``path`` for writing (truncated), readable and writable by its owner only, also
    when it existed with a wider mode."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(descriptor, 0o600)
    return os.fdopen(descriptor, mode, **options)


def _local(name: str, timestamp: float, calendar: LocalCalendar | None) -> dict[str, str]:
    """``{name: local ISO time}`` beside an epoch time (nothing without a calendar)."""
    return {} if calendar is None else {name: calendar.iso(timestamp)}


def _cell(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else ""
    return value


def json_safe(value: Any) -> Any:
    """NaN and infinity become null (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    return value
