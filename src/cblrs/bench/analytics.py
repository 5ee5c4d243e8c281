"""Analytics speed: an hour of a busy site, offline in one go and online update by update.

The site is a 60 x 40 m square with four counting lines and four zones; ``tracks`` people
are always present, each id living ``life_s`` seconds (staggered) before a new id takes its
slot, walking straight lines folded back at the borders with 5 cm of jitter, reported at
``rate_hz``. Offline: :func:`cblrs.analytics.tables.analyse_tracks` on every row. Online: one
:meth:`cblrs.analytics.Analytics.update` per instant, for the first ``online_minutes``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from cblrs.analytics import Analytics, AnalyticsConfig, HeatmapGrid
from cblrs.analytics.tables import analyse_tracks
from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.detections import Tracks
from cblrs.places import Places

AREA_M = (60.0, 40.0)


def bench_places() -> Places:
    """Four lines and four zones over the benchmark's 60 x 40 m square."""
    return Places.from_dict({
        "zones": [
            {"name": "north_west", "polygon": [[2, 22], [28, 22], [28, 38], [2, 38]]},
            {"name": "north_east", "polygon": [[32, 22], [58, 22], [58, 38], [32, 38]]},
            {"name": "south_west", "polygon": [[2, 2], [28, 2], [28, 18], [2, 18]]},
            {"name": "centre",
             "polygon": [[20, 12], [40, 12], [45, 20], [40, 28], [20, 28], [15, 20]]},
        ],
        "lines": [
            {"name": "x15", "start": [15, 0], "end": [15, 40]},
            {"name": "x30", "start": [30, 0], "end": [30, 40]},
            {"name": "x45", "start": [45, 0], "end": [45, 40]},
            {"name": "y20", "start": [0, 20], "end": [60, 20]},
        ],
    })


def crowd_tracks(
    tracks: int = 200, seconds: float = 3600.0, rate_hz: float = 10.0, life_s: float = 60.0,
    seed: int = 0,
) -> Tracks:
    """``tracks`` walkers present at every instant, rows sorted by time."""
    rng = np.random.default_rng(seed)
    times = np.arange(round(seconds * rate_hz)) / rate_hz
    offset = rng.uniform(0, life_s, tracks)  # staggered births
    life = np.floor((times[:, None] + offset[None, :]) / life_s).astype(np.int64)  # (T, S)
    track_id = life * tracks + np.arange(tracks)[None, :] + 1
    lives = int(life.max()) + 1
    start = rng.uniform(0, 1, (lives, tracks, 2)) * np.array(AREA_M)
    heading = rng.uniform(-np.pi, np.pi, (lives, tracks))
    speed = rng.uniform(0.8, 1.6, (lives, tracks))
    velocity = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * speed[..., None]
    born = (life * life_s - offset[None, :])[..., None]  # (T, S, 1)
    age = times[:, None, None] - born
    slot = np.arange(tracks)[None, :]
    raw = start[life, slot] + velocity[life, slot] * age
    size = np.array(AREA_M)
    folded = np.abs((raw % (2 * size)) - size)  # walk back and forth inside the square
    xy = size - folded + rng.normal(0, 0.05, raw.shape)
    count = len(times) * tracks
    return Tracks(
        frame=np.repeat(np.arange(len(times)), tracks),
        timestamp=np.repeat(times, tracks),
        track_id=track_id.reshape(count),
        world_xy=xy.reshape(count, 2),
        class_id=np.zeros(count, np.int64),
    )


def benchmark_analytics(
    tracks: int = 200, hours: float = 1.0, rate_hz: float = 10.0, online_minutes: float = 5.0,
) -> dict[str, Any]:
    """Offline and online analytics timings (see the module docstring)."""
    seconds = hours * 3600.0
    start = time.perf_counter()
    rows = crowd_tracks(tracks, seconds, rate_hz)
    generate_s = time.perf_counter() - start
    places = bench_places()
    config = AnalyticsConfig(heatmap=HeatmapGrid((0.0, 0.0), AREA_M, 0.5), interval_s=60.0)

    start = time.perf_counter()
    result = analyse_tracks(rows, places, config)
    offline_s = time.perf_counter() - start

    engine = Analytics(places, config)
    instants = round(min(online_minutes * 60.0, seconds) * rate_hz)
    per_update = np.empty(instants)
    for index in range(instants):
        chunk = rows[index * tracks:(index + 1) * tracks]
        begin = time.perf_counter()
        engine.update(chunk)
        per_update[index] = time.perf_counter() - begin
    crossings = sum(row["count"] for row in result.lines if row["class"] == "all")
    return json_ready({
        "machine": machine_info(),
        "tracks": tracks, "hours": hours, "rate_hz": rate_hz, "rows": len(rows),
        "track_ids": len(np.unique(rows.track_id)),
        "lines": len(places.lines), "zones": len(places.zones),
        "generate_s": generate_s,
        "offline_s": offline_s,
        "offline_rows_per_s": len(rows) / offline_s,
        "offline_realtime_factor": seconds / offline_s,
        "online_updates": instants,
        "online_update_ms_median": float(np.median(per_update) * 1e3),
        "online_update_ms_p99": float(np.percentile(per_update, 99) * 1e3),
        "online_realtime_factor": (instants / rate_hz) / float(per_update.sum()),
        "crossings": crossings,
        "visits": sum(row["visits"] for row in result.zones),
    })


def analytics_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_analytics`'s result."""
    return "\n".join([
        f"### Analytics speed ({result['tracks']} live tracks at {result['rate_hz']:g} Hz for "
        f"{result['hours']:g} h: {result['rows']:,} rows, {result['track_ids']:,} ids, "
        f"{result['lines']} lines, {result['zones']} zones, 0.5 m heatmap)",
        "",
        describe_machine(result["machine"]),
        "",
        "| mode | figure |",
        "|---|---|",
        f"| offline (`analyse_tracks`, one process) | {result['offline_s']:.1f} s, "
        f"{result['offline_rows_per_s']:,.0f} rows/s, "
        f"{result['offline_realtime_factor']:.0f}x real time |",
        f"| online (`Analytics.update` per instant, first {result['online_updates']:,} "
        f"updates) | median {result['online_update_ms_median']:.2f} ms, "
        f"p99 {result['online_update_ms_p99']:.2f} ms per update of {result['tracks']} rows, "
        f"{result['online_realtime_factor']:.0f}x real time |",
        "",
        f"Counted {result['crossings']:,} crossings and {result['visits']:,} visits. "
        "Timings on a shared machine: compare ratios, not absolute times.",
    ])
