"""Linker speed: how many plane track rows one linker takes per second, alone and as a service.

The load is a street of ``planes`` planes in a row (44 m each, overlapping their neighbours by
6 m, 30 m across), on average ``people`` people on each, walking along the street at
0.8-1.6 m/s for ``life_s`` seconds each (staggered) and replaced by a newcomer, reported at
``rate_hz`` by every plane whose rectangle holds them (5 cm of noise, each plane's own ids):
people cross planes all the time, so the linker decides hand-overs all the time.

* **linker**: :class:`~cblrs.linking.PlaneLinker` alone, fed instant by instant as a live
  linker is (every plane's rows of the instant, then the watermark): rows per second, and the
  time per instant;
* **service**: :class:`~cblrs.runtime.outputs.linker_service.LinkerService` on the in-process broker
  with its SQLite file and the site's analytics (one counting line per plane): every plane's
  updates published as fast as they go, timed from the first publish to the last update
  committed (decode, de-duplication, linking, counting, one transaction per batch,
  acknowledgements, global tracks published).

Every global id is checked against the people: the share of global rows whose id is that of
the person they belong to (an id's majority person) is printed with the speed.
"""

from __future__ import annotations

import math
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.detections import Tracks
from cblrs.linking.links import PlaneLink
from cblrs.plane import PlaneSet, PlaneSpec

PLANE_LENGTH_M = 44.0
OVERLAP_M = 6.0
WIDTH_M = 30.0


def street_planes(planes: int) -> PlaneSet:
    """``planes`` planes in a row along x, each overlapping the next by :data:`OVERLAP_M`."""
    step = PLANE_LENGTH_M - OVERLAP_M
    return PlaneSet(PlaneSpec(index + 1, (index * step, 0.0), PLANE_LENGTH_M, WIDTH_M)
                    for index in range(planes))


def street_links(planes: PlaneSet) -> tuple[PlaneLink, ...]:
    """Each plane linked to the next by their overlap."""
    return tuple(PlaneLink.overlap(planes[index], planes[index + 1])
                 for index in range(len(planes) - 1))


def street_load(
    planes: int = 8, people: int = 50, seconds: float = 120.0, rate_hz: float = 10.0,
    life_s: float = 60.0, seed: int = 0,
) -> tuple[PlaneSet, dict[int, Tracks], dict[tuple[int, int], int]]:
    """Every plane's rows of the street (see the module docstring).

    Returns:
        ``(planes, rows per plane sorted by time, {(plane, local id): person})``.
    """
    rng = np.random.default_rng(seed)
    spec = street_planes(planes)
    length = planes * (PLANE_LENGTH_M - OVERLAP_M) + OVERLAP_M
    slots = max(1, round(people * length / PLANE_LENGTH_M))
    times = np.arange(round(seconds * rate_hz)) / rate_hz
    offset = rng.uniform(0, life_s, slots)
    life = np.floor((times[:, None] + offset[None, :]) / life_s).astype(np.int64)  # (T, S)
    person = life * slots + np.arange(slots)[None, :]
    lives = int(life.max()) + 1
    start = np.stack([rng.uniform(0, length, (lives, slots)),
                      rng.uniform(2, WIDTH_M - 2, (lives, slots))], axis=-1)
    speed = rng.uniform(0.8, 1.6, (lives, slots)) * rng.choice([-1.0, 1.0], (lives, slots))
    born = life * life_s - offset[None, :]
    age = times[:, None] - born
    column = np.arange(slots)[None, :]
    x = start[life, column, 0] + speed[life, column] * age
    y = np.broadcast_to(start[life, column, 1], x.shape)
    xy = np.stack([x, y], axis=-1) + rng.normal(0, 0.05, (*x.shape, 2))
    per_plane: dict[int, Tracks] = {}
    owner: dict[tuple[int, int], int] = {}
    flat_xy = xy.reshape(-1, 2)
    frame = np.repeat(np.arange(len(times)), slots)
    stamp = np.repeat(times, slots)
    who = person.reshape(-1)
    for plane in spec:
        inside = plane.contains(flat_xy)
        local = who[inside] * planes + plane.plane_id  # each plane numbers its own tracks
        per_plane[plane.plane_id] = Tracks(frame[inside], stamp[inside], local,
                                           flat_xy[inside], class_id=np.zeros(len(local), int))
        owner.update(zip(zip([plane.plane_id] * len(local), local.tolist(), strict=True),
                         who[inside].tolist(), strict=True))
    return spec, per_plane, owner


def id_purity(track_id: np.ndarray, person: np.ndarray) -> float:
    """The share of rows whose global id's majority person is theirs (1: ids never mix)."""
    if len(track_id) == 0:
        return math.nan
    pairs, counts = np.unique(np.stack([track_id, person], axis=1), axis=0, return_counts=True)
    best: dict[int, int] = {}
    for (global_id, _), count in zip(pairs.tolist(), counts.tolist(), strict=True):
        best[global_id] = max(best.get(global_id, 0), count)
    return sum(best.values()) / len(track_id)


def _instants(per_plane: dict[int, Tracks]) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    times = np.unique(np.concatenate([tracks.timestamp for tracks in per_plane.values()]))
    bounds = {plane: np.searchsorted(tracks.timestamp, times, side="right")
              for plane, tracks in per_plane.items()}
    return times, bounds


def run_linker(spec: PlaneSet, per_plane: dict[int, Tracks], delay_s: float = 0.5
               ) -> dict[str, Any]:
    """The linker alone, instant by instant (see the module docstring)."""
    from cblrs.linking.linker import LinkedRows, PlaneLinker

    linker = PlaneLinker(spec, street_links(spec))
    times, bounds = _instants(per_plane)
    per_instant = np.empty(len(times))
    parts = []
    cursor = dict.fromkeys(per_plane, 0)
    started = time.perf_counter()
    for index, instant in enumerate(times.tolist()):
        begin = time.perf_counter()
        for plane, tracks in per_plane.items():
            stop = int(bounds[plane][index])
            linker.push(plane, tracks[cursor[plane]:stop])
            cursor[plane] = stop
        parts.append(linker.advance(instant - delay_s))
        per_instant[index] = time.perf_counter() - begin
    parts.append(linker.finish())
    elapsed = time.perf_counter() - started
    rows = LinkedRows.concatenate(parts)
    return {"seconds": elapsed, "rows_in": int(sum(len(t) for t in per_plane.values())),
            "rows_out": len(rows), "rows": rows,
            "instant_ms_median": float(np.median(per_instant) * 1e3),
            "instant_ms_p99": float(np.percentile(per_instant, 99) * 1e3),
            "handovers": int(linker.counters.get("handovers_overlap", 0))}


def run_service(spec: PlaneSet, per_plane: dict[int, Tracks], timeout_s: float = 600.0
                ) -> dict[str, Any]:
    """The linker service on the in-process broker with SQLite and analytics."""
    from cblrs.linking.linker import PlaneLinker
    from cblrs.places import CountingLine, Places
    from cblrs.runtime.outputs.linker_service import LinkerService
    from cblrs.runtime.outputs.linker_store import LinkerStore
    from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
    from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
    from cblrs.runtime.transport.topics import tracks_topic
    from cblrs.runtime.wire import encode_tracks

    places = Places(lines=tuple(
        CountingLine(f"line_{plane.plane_id}",
                     np.array([plane.origin[0] + plane.width / 2, 1.0]),
                     np.array([plane.origin[0] + plane.width / 2, WIDTH_M - 1.0]))
        for plane in spec))
    times, bounds = _instants(per_plane)
    epoch = time.time() - float(times[-1]) - 60.0
    payloads = []
    cursor = dict.fromkeys(per_plane, 0)
    for index, instant in enumerate(times.tolist()):
        for plane, tracks in per_plane.items():
            stop = int(bounds[plane][index])
            chunk = tracks[cursor[plane]:stop]
            cursor[plane] = stop
            chunk = Tracks(chunk.frame, chunk.timestamp + epoch, chunk.track_id,
                           chunk.world_xy, class_id=chunk.class_id)
            payloads.append((plane, encode_tracks(chunk, plane, sequence=index,
                                                  timestamp=epoch + instant)))
    encoded_bytes = sum(len(payload) for _, payload in payloads)
    with tempfile.TemporaryDirectory() as folder:
        broker = InProcessBroker()
        store = LinkerStore(Path(folder) / "linker.db")
        service = LinkerService(
            InProcessTransport(broker, "linker", persistent=True), store,
            PlaneLinker(spec, street_links(spec)), spec.ids,
            analytics=OnlineAnalytics(places, delay_s=0.0), live_interval_s=None)
        service.start()
        publishers = {plane: InProcessTransport(broker, f"matcher{plane}") for plane in spec.ids}
        for transport in publishers.values():
            transport.connect()
        started = time.perf_counter()
        for plane, payload in payloads:
            publishers[plane].publish(tracks_topic(plane), payload)
        deadline = time.monotonic() + timeout_s
        while service.stats().get("updates", 0) < len(payloads):
            if time.monotonic() > deadline or service.failed() is not None:
                raise RuntimeError(f"the linker service took {service.stats().get('updates')} "
                                   f"of {len(payloads)} updates")
            time.sleep(0.05)
        elapsed = time.perf_counter() - started
        service.close(finish=True)
        database_bytes = sum(path.stat().st_size for path in Path(folder).iterdir()
                             if path.name.startswith("linker.db"))
        rows = store.rows()
        counters = store.counters()
        store.close()
        for transport in publishers.values():
            transport.close()
    return {"seconds": elapsed, "updates": len(payloads), "rows_out": len(rows),
            "rows_in": int(sum(len(t) for t in per_plane.values())),
            "wire_bytes": encoded_bytes, "database_bytes": database_bytes,
            "rows_stored": counters.get("rows_out", 0)}


def benchmark_linker(planes: int = 8, people: int = 50, seconds: float = 120.0,
                     rate_hz: float = 10.0, service: bool = True) -> dict[str, Any]:
    """Linker speed on a street (see the module docstring)."""
    start = time.perf_counter()
    spec, per_plane, owner = street_load(planes, people, seconds, rate_hz)
    generate_s = time.perf_counter() - start
    alone = run_linker(spec, per_plane)
    rows = alone.pop("rows")
    person = np.array([owner[(plane, track)] for plane, track in zip(
        rows.plane_id.tolist(), rows.local_track_id.tolist(), strict=True)])
    people_total = len(set(owner.values()))
    result: dict[str, Any] = {
        "machine": machine_info(), "planes": planes, "people_per_plane": people,
        "people": people_total, "seconds": seconds, "rate_hz": rate_hz,
        "generate_s": generate_s,
        "linker": {**alone, "rows_per_s": alone["rows_in"] / alone["seconds"],
                   "realtime_factor": seconds / alone["seconds"],
                   "global_ids": len(np.unique(rows.tracks.track_id)),
                   "id_purity": id_purity(rows.tracks.track_id, person)},
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    if service:
        served = run_service(spec, per_plane)
        result["service"] = {**served, "rows_per_s": served["rows_in"] / served["seconds"],
                             "updates_per_s": served["updates"] / served["seconds"],
                             "realtime_factor": seconds / served["seconds"],
                             "database_bytes_per_row": served["database_bytes"]
                             / max(served["rows_out"], 1),
                             "wire_bytes_per_row": served["wire_bytes"]
                             / max(served["rows_in"], 1)}
        result["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return json_ready(result)


def linker_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_linker`'s result."""
    linker = result["linker"]
    lines = [
        f"### Linker speed ({result['planes']} planes in a row, {result['people_per_plane']} "
        f"people on each, {result['rate_hz']:g} Hz for {result['seconds']:g} s: "
        f"{linker['rows_in']:,} plane rows, {result['people']:,} people)",
        "",
        describe_machine(result["machine"]),
        "",
        "| part | rows/s | real time | figures |",
        "|---|---:|---:|---|",
        f"| linker alone (`PlaneLinker`, instant by instant) | {linker['rows_per_s']:,.0f} | "
        f"{linker['realtime_factor']:.1f}x | {linker['instant_ms_median']:.2f} / "
        f"{linker['instant_ms_p99']:.2f} ms per instant (median / p99), "
        f"{linker['handovers']:,} hand-overs, {linker['global_ids']:,} global ids, id purity "
        f"{100 * linker['id_purity']:.2f} % |",
    ]
    if "service" in result:
        served = result["service"]
        lines.append(
            f"| service (in-process broker, SQLite, analytics) | {served['rows_per_s']:,.0f} "
            f"| {served['realtime_factor']:.1f}x | {served['updates_per_s']:,.0f} updates/s; "
            f"{served['wire_bytes_per_row']:.0f} B per row on the wire, "
            f"{served['database_bytes_per_row']:.0f} B per global row in its database |")
    lines += ["", f"Peak memory of the process: {result['max_rss_mb']:.0f} MB. One core; "
              "timings on a shared machine: compare ratios, not absolute times. Command: "
              "`cblrs bench linker`."]
    return "\n".join(lines)
