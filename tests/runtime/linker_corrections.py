"""A plane's correction fed to the linker in random batches: the scenario of the linker's
correction tests, and its cost (relinks, rows linked again, CPU seconds of the linking).

Plane 2's matcher got messages late (:func:`wrong_then_corrected`): the linker links its
wrong rows, then gets the right ones as a correction, interleaved in random batches with
every other plane's updates (:func:`run_correction`; each plane's updates in their order, as
one matcher publishes them), optionally stopping and starting again halfway through the
correction. The final rows and hand-overs must be the offline link's of the right rows.

    PYTHONPATH=$PWD/src python tests/runtime/linker_corrections.py --seeds 40 [--restart]

prints, per seed, the relinks, the global rows linked again and the CPU seconds of the
linking thread, then their medians.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.datasets.city import city_scenes, street_world
from cblrs.linking.files import site_analytics_config
from cblrs.linking.linker import PlaneLinker, link_tracks
from cblrs.runtime.outputs.linker_service import LinkerService
from cblrs.runtime.outputs.linker_store import LinkerStore
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.topics import tracks_topic
from cblrs.runtime.wire import encode_tracks

EPOCH = 1_700_000_000.0
SINCE, UNTIL = EPOCH + 30.0, EPOCH + 38.0
"""Plane 2's matcher got messages late: its rows from SINCE to UNTIL were wrong."""


def small_city() -> tuple[Any, dict[int, Any]]:
    """The small city's planes as matchers would publish them: every plane's ground truth
    with its own ids and 5 cm of noise, at capture times from EPOCH."""
    scenes = city_scenes(street_world(seed=4, people=10, cars=4, wanderers=1, spawn_s=6.0,
                                      max_trip_m=90.0))
    rng = np.random.default_rng(1)
    per_plane = {}
    for plane_id, scene in scenes.planes.items():
        truth = scene.ground_truth
        per_plane[plane_id] = replace(
            truth, timestamp=EPOCH + truth.timestamp, track_id=truth.track_id * 10 + plane_id,
            world_xy=truth.world_xy + rng.normal(0, 0.05, (len(truth), 2)))
    return scenes, per_plane


def updates_of(scenes: Any, per_plane: dict[int, Any]) -> list[tuple[float, int, bytes]]:
    """Every plane's updates, one per frame (empty ones too), in capture order."""
    updates = []
    for plane_id, rows in per_plane.items():
        for index, seconds in enumerate(scenes.timestamps.tolist()):
            chosen = rows[rows.frame == index]
            updates.append((EPOCH + seconds, plane_id, encode_tracks(
                chosen, plane_id, sequence=index, timestamp=EPOCH + seconds)))
    updates.sort(key=lambda item: (item[0], item[1]))
    return updates


def wrong_then_corrected(scenes: Any, per_plane: dict[int, Any]
                         ) -> tuple[list[tuple[float, int, bytes]], int, list[bytes]]:
    """What plane 2's matcher publishes when it got messages late: first, with every other
    plane's, its wrong rows (from SINCE to UNTIL other track ids — a split — and 40 cm off);
    after update ``cut`` of those, it re-tracks and publishes the right rows of every group
    after SINCE up to its clock with ``corrected_from`` = SINCE."""
    truth = per_plane[2]
    window = (truth.timestamp > SINCE) & (truth.timestamp <= UNTIL)
    first = updates_of(scenes, {**per_plane, 2: replace(
        truth, track_id=np.where(window, truth.track_id + 1000, truth.track_id),
        world_xy=truth.world_xy + np.where(window[:, None], 0.4, 0.0))})
    cut = next(index for index, item in enumerate(first) if item[0] > UNTIL + 12.0)
    clock = max(item[0] for item in first[:cut] if item[1] == 2)
    corrected = [encode_tracks(truth[truth.frame == index], 2, sequence=100_000 + index,
                               timestamp=EPOCH + seconds, corrected_from=SINCE)
                 for index, seconds in enumerate(scenes.timestamps.tolist())
                 if SINCE < EPOCH + seconds <= clock]
    return first, cut, corrected


def make_service(broker: Any, scenes: Any, database: Path, **options: Any) -> LinkerService:
    spec = scenes.spec
    transport = InProcessTransport(broker, "linker", persistent=True)
    analytics = OnlineAnalytics(spec.places, site_analytics_config(spec.links), delay_s=0.0)
    return LinkerService(transport, LinkerStore(database), PlaneLinker(spec.planes, spec.links),
                         spec.planes.ids, site={"planes": spec.planes.to_list()},
                         analytics=analytics, live_interval_s=None, **options)


class DirectDelivery:
    """A delivery handed to the service's `_process` directly."""

    def __init__(self, topic: str, payload: bytes):
        self.topic, self.payload = topic, payload

    def ack(self) -> None:
        pass


def run_correction(city: tuple[Any, dict[int, Any]], folder: Path, seed: int,
                   restart: bool = False) -> tuple[LinkerService, dict[str, float]]:
    """Plane 2's correction in random batches (see the module); with ``restart``, the service
    stops and starts again after a random part of the correction. Returns the finished
    service (its store still open: the caller closes it) and the cost: ``relinks``,
    ``rows_linked_again``, ``cpu_s`` (the linking's thread CPU seconds) and
    ``correction_cpu_s`` (of it, from the correction's first update on)."""
    scenes, per_plane = city
    first, cut, corrected = wrong_then_corrected(scenes, per_plane)
    rng = random.Random(seed)
    broker = InProcessBroker()
    database = folder / f"linker-{seed}-{int(restart)}.db"
    service = make_service(broker, scenes, database)
    service.start()
    cpu = [0.0]
    taken = [0]
    restart_after = rng.randint(1, len(corrected) - 1) if restart else None

    def feed(streams: dict[int, list], stop: Any = lambda: False) -> dict[int, list]:
        """Random batches of the planes' streams, each plane's in its order."""
        nonlocal service, restart_after
        while any(streams.values()) and not stop():
            batch = []
            for _ in range(rng.randint(1, 40)):
                planes = [plane for plane, stream in streams.items() if stream]
                if planes:
                    marker, plane, payload = streams[rng.choice(planes)].pop(0)
                    taken[0] += marker is None
                    batch.append((DirectDelivery(tracks_topic(plane), payload), time.time()))
            started = time.thread_time()
            service._process(batch)
            cpu[0] += time.thread_time() - started
            if restart_after is not None and taken[0] >= restart_after:
                service.close()  # a stop, not the end: the next start resumes
                service.store.close()
                service = make_service(broker, scenes, database)
                service.start()
                restart_after = None
        return streams

    try:
        rest = feed({plane: [item for item in first[:cut] if item[1] == plane]
                     for plane in sorted(per_plane)}, stop=lambda: service.linker.clock > UNTIL)
        later = {plane: rest[plane] + [item for item in first[cut:] if item[1] == plane]
                 for plane in sorted(per_plane) if plane != 2}
        later[2] = rest[2] + [(None, 2, payload) for payload in corrected] + [
            item for item in first[cut:] if item[1] == 2]
        before = cpu[0]
        feed(later)
        later_cpu = cpu[0] - before
        started = time.thread_time()
        service.close(finish=True)
        cpu[0] += time.thread_time() - started
    except BaseException:
        service.stop()
        service.store.close()
        raise
    counters = service.store.counters()
    return service, {"relinks": counters.get("relinks", 0),
                     "rows_linked_again": counters.get("rows_linked_again", 0),
                     "cpu_s": cpu[0], "correction_cpu_s": later_cpu}


def offline_link(city: tuple[Any, dict[int, Any]]) -> tuple[Any, list]:
    """The offline link of the right rows: its global rows and hand-overs."""
    scenes, per_plane = city
    offline, handovers, _ = link_tracks(scenes.spec.planes, scenes.spec.links, per_plane)
    return offline, handovers


def same_rows(live: Any, offline: Any) -> bool:
    return all(np.array_equal(getattr(live.tracks, name), getattr(offline.tracks, name))
               for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=40, help="seeds 0..N-1 (default 40)")
    parser.add_argument("--restart", action="store_true",
                        help="stop and start again halfway through the correction")
    options = parser.parse_args(argv)
    city = small_city()
    offline, handovers = offline_link(city)
    costs = []
    wrong = 0
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(options.seeds):
            service, cost = run_correction(city, Path(folder), seed, options.restart)
            equal = same_rows(service.store.rows(), offline) and (
                service.store.handovers() == handovers)
            service.store.close()
            wrong += not equal
            costs.append(cost)
            print(f"seed {seed:3d}: relinks {cost['relinks']:3d}  rows linked again "
                  f"{cost['rows_linked_again']:6d}  cpu {cost['cpu_s']:.2f} s (from the "
                  f"correction on {cost['correction_cpu_s']:.2f} s)"
                  f"{'' if equal else '  DIFFERS from the offline link'}", flush=True)
    for name in ("relinks", "rows_linked_again", "cpu_s", "correction_cpu_s"):
        values = [cost[name] for cost in costs]
        print(f"{name}: median {statistics.median(values):g}, min {min(values):g}, "
              f"max {max(values):g}")
    print(f"{wrong} of {len(costs)} differ from the offline link")
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
