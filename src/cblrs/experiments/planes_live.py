"""The city of ``cblrs experiment planes`` run live on a 3-node NATS cluster, with a fault.

The street of :mod:`cblrs.datasets.city` is written as a site file and every plane's cameras
are rendered to references; then, on a :class:`~cblrs.runtime.broker.nats_server.NatsCluster`
of three nodes:

1. one ``cblrs matcher --backbone nats://...`` per plane starts, then, once they are up,
   ``cblrs linker --site ... --backbone nats://...`` (processes);
2. one camera node per camera (threads, paced in real time: the fusion tracker's ages and
   motion models are in seconds) publishes its plane's messages to JetStream;
3. once the chosen plane's matcher has tracked a share of its messages it is killed
   (SIGKILL) and a new one starts on another "host" (another ``--db`` and client id), which
   takes over the plane's lease and rebuilds its store from the stream;
4. everything ends: the cameras say "offline", the matchers exit, the linker finishes after
   ``linker_idle_s`` without updates.

:func:`run_live_city` returns where everything is stored (the planes' final databases, the
linker's); :func:`live_city_figures` scores them as ``cblrs experiment planes`` scores its
offline tracks (linked IDF1 against the pooled single-plane IDF1, OD error against the
ground truth) and checks that the linker's rows equal the offline link of the planes' stored
tracks. ``tests/runtime/test_runtime_city_nats.py`` and ``scripts/city_nats.py`` run it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets.city import CityScenes, city_scenes, city_site_document, street_world
from cblrs.detections import Tracks
from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.counts import count_errors
from cblrs.experiments.planes import pooled_idf1
from cblrs.linking.files import site_analytics_config
from cblrs.linking.linker import link_tracks
from cblrs.pipeline import render_scene_references
from cblrs.reference import ReferenceImage
from cblrs.site import save_document


@dataclass(frozen=True)
class LiveCitySetup:
    """What :func:`run_live_city` runs.

    Attributes:
        world: keyword arguments of :func:`~cblrs.datasets.city.street_world`.
        kill_plane: the plane whose matcher host dies (None: no fault).
        kill_share: it dies once it has tracked this share of its messages.
        speed: replay speed (1: real time, what the tracker is tuned for).
        window_s: the matchers' ``--window``.
        lease_ttl_s: the matchers' ``--lease-ttl``.
        linker_idle_s: the linker's ``--idle-exit``.
        timeout_s: longest wait for any one step (a loaded machine is slow).
    """

    world: dict[str, Any] = field(
        default_factory=lambda: {
            "seed": 6,
            "people": 2,
            "cars": 4,
            "wanderers": 0,
            "spawn_s": 3.0,
            "max_trip_m": 90.0,
            "fps": 4.0,
        }
    )
    kill_plane: int | None = 3
    kill_share: float = 0.25
    speed: float = 1.0
    window_s: float = 30.0
    lease_ttl_s: float = 3.0
    linker_idle_s: float = 20.0
    timeout_s: float = 240.0


@dataclass(frozen=True, eq=False)
class LiveCity:
    """A city written for its services: site file and references (one folder per plane)."""

    scenes: CityScenes
    folder: Path
    site: Path
    references: dict[int, list[ReferenceImage]]


@dataclass
class LiveCityRun:
    """Where a live run stored everything, and what happened on the way.

    Attributes:
        city: the city.
        epoch: capture time of the city's time 0 (seconds since the Unix epoch).
        databases: plane -> the final matcher database of the plane.
        linker_database: the linker's database.
        killed_plane: the plane whose matcher was killed (None without a fault).
        processed_at_kill: messages the killed matcher had tracked (None without a fault).
        recover_s: from the kill until the new host had re-tracked as much, seconds.
        matcher_summaries: plane -> the final matcher's JSON summary.
        linker_summary: the linker's JSON summary.
        cameras_flushed: whether every camera's messages were acknowledged by the stream.
        seconds: wall time of the run.
    """

    city: LiveCity
    epoch: float
    databases: dict[int, Path]
    linker_database: Path
    killed_plane: int | None = None
    processed_at_kill: int | None = None
    recover_s: float | None = None
    matcher_summaries: dict[int, dict[str, Any]] = field(default_factory=dict)
    linker_summary: dict[str, Any] = field(default_factory=dict)
    cameras_flushed: bool = False
    seconds: float = 0.0


def prepare_city(world: dict[str, Any], folder: Path) -> LiveCity:
    """Build the street, write its site file and every plane's references into ``folder``."""
    scenes = city_scenes(street_world(**world))
    folder.mkdir(parents=True, exist_ok=True)
    site = save_document(city_site_document(scenes.spec), folder / "street.yaml")
    references: dict[int, list[ReferenceImage]] = {}
    for plane_id, scene in scenes.planes.items():
        plane_folder = folder / f"plane{plane_id}"
        plane_folder.mkdir(exist_ok=True)
        references[plane_id] = []
        for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
            path = reference.save(plane_folder / f"{camera.name}.png")
            references[plane_id].append(ReferenceImage.load(path, expected_size=camera.image_size))
    return LiveCity(scenes, folder, site, references)


def wait_for(condition: Callable[[], object], timeout: float, what: str) -> None:
    """Poll ``condition`` every 50 ms; TimeoutError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def _service(arguments: list[str], log: Path) -> subprocess.Popen:
    """Start ``cblrs ...``; its stdout (the JSON summary) on a pipe, its log in ``log``.

    The log goes to a file, not a pipe read only at the end: a service that logged more than
    a pipe holds (64 KiB) would block in its next log call, and the log of a service that
    made no progress is read while it still runs (:func:`_log_tail`)."""
    with open(log, "a", encoding="utf-8") as stderr:  # the child keeps its own descriptor
        return subprocess.Popen(
            [sys.executable, "-m", "cblrs.cli.main", *arguments],
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def _log_of(database: Path) -> Path:
    """Where the service writing ``database`` logs (beside it)."""
    return database.with_suffix(".log")


def _log_tail(log: Path, characters: int = 3000) -> str:
    try:
        return log.read_text(encoding="utf-8", errors="replace")[-characters:]
    except OSError:
        return "(no log)"


def matcher_options(city: LiveCity, plane_id: int) -> dict[str, Any]:
    """The fusion tracker's options a plane's ``cblrs matcher --site`` runs with (the
    cameras' positions from the site file): give them to an in-process run to compare."""
    from cblrs.site import load_site

    names = city.scenes.planes[plane_id].camera_names
    positions = load_site(city.site).camera_positions()
    return {"camera_positions": {name: list(positions[name]) for name in names}}


def start_matcher(
    city: LiveCity,
    url: str,
    plane_id: int,
    database: Path,
    client_id: str,
    setup: LiveCitySetup,
    *extra: str,
) -> subprocess.Popen:
    """``cblrs matcher`` for one plane: the site file (the cameras' positions), the plane's
    references, its cameras in the scene's order (as the in-process tracker has them: within
    a time the tracker takes messages in this order). The site's places are counted by the
    linker, not by the planes."""
    return _service(
        [
            "matcher",
            "--site",
            str(city.site),
            "--no-analytics",
            "--references",
            str(city.folder / f"plane{plane_id}"),
            "--plane",
            str(plane_id),
            "--cameras",
            ",".join(city.scenes.planes[plane_id].camera_names),
            "--db",
            str(database),
            "--backbone",
            url,
            "--client-id",
            client_id,
            "--window",
            str(setup.window_s),
            "--lease-ttl",
            str(setup.lease_ttl_s),
            "--until-cameras-offline",
            "--idle-exit",
            str(setup.timeout_s),
            "--json",
            *extra,
        ],
        _log_of(database),
    )


def start_linker(
    city: LiveCity, url: str, database: Path, setup: LiveCitySetup
) -> subprocess.Popen:
    """``cblrs linker`` for the city's site (waits as long as a take-over may take)."""
    return _service(
        [
            "linker",
            "--site",
            str(city.site),
            "--db",
            str(database),
            "--backbone",
            url,
            "--client-id",
            "linker",
            "--max-wait",
            str(10 * setup.timeout_s),
            "--idle-exit",
            str(setup.linker_idle_s),
            "--live-interval",
            "0",
            "--json",
        ],
        _log_of(database),
    )


def start_cameras(
    city: LiveCity, url: str, epoch: float, speed: float
) -> tuple[list[threading.Thread], list[bool]]:
    """One paced camera node per camera of every plane, each with its own NATS connection
    (threads). Returns the threads and the list each appends to whether the stream
    acknowledged all its messages."""
    # lazy: nats-py is an extra; only a live run needs it
    from cblrs.runtime.camera.camera_node import CameraNode
    from cblrs.runtime.camera.sources import scene_source
    from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport

    settings = NatsSettings.from_url(url)
    threads = []
    results: list[bool] = []
    for plane_id, scene in city.scenes.planes.items():
        for index, name in enumerate(scene.camera_names):

            def run(plane_id=plane_id, scene=scene, index=index, name=name) -> None:
                transport = NatsTransport(f"camera-{name}", settings)
                transport.connect()
                node = CameraNode(
                    transport,
                    plane_id,
                    name,
                    city.references[plane_id][index],
                    realtime=True,
                    speed=speed,
                    epoch=epoch,
                    flush_timeout_s=240.0,
                )
                report = node.run(scene_source(scene, index), connect=False)
                results.append(report.flushed)
                transport.close()

            thread = threading.Thread(target=run, daemon=True)
            thread.start()
            threads.append(thread)
    return threads, results


def store_counter(database: Path, name: str) -> int:
    """A counter of a matcher database being written (0 until it exists)."""
    from cblrs.runtime.matcher.store import RuntimeStore
    from cblrs.runtime.matcher.store_file import StoreNotReady

    if not database.exists():
        return 0
    try:
        with RuntimeStore(database, read_only=True) as store:
            return store.counters().get(name, 0)
    except StoreNotReady:
        return 0


def _consumer_ready(probe: Any, plane_id: int) -> bool:
    from cblrs.runtime.transport.nats_subjects import detections_stream

    try:
        probe.call(
            probe.jetstream.consumer_info(detections_stream(plane_id), f"cblrs-plane-{plane_id}"), 5
        )
        return True
    except Exception:
        return False


def _jetstream_ready(probe: Any) -> bool:
    try:
        probe.call(probe.jetstream.account_info(), 5)
        return True
    except Exception:
        return False


def _ended(process: subprocess.Popen, what: str, log: Path) -> None:
    if process.poll() is not None:
        raise RuntimeError(f"{what} ended: {_log_tail(log)}")


def _wait_for_service(
    condition: Callable[[], object], timeout: float, what: str, log: Path
) -> None:
    """:func:`wait_for`, and on a timeout the end of the log of the service waited for."""
    try:
        wait_for(condition, timeout, what)
    except TimeoutError as error:
        raise TimeoutError(f"{error}; its log ends: {_log_tail(log)}") from None


def run_live_city(
    city: LiveCity,
    url: str,
    probe: Any,
    folder: Path,
    setup: LiveCitySetup | None = None,
    report: Callable[[str], None] | None = None,
) -> LiveCityRun:
    """Run the city's services on the cluster at ``url`` with the fault of ``setup``.

    Args:
        city: from :func:`prepare_city`.
        url: the cluster's ``nats://`` URL(s).
        probe: a connected :class:`~cblrs.runtime.transport.nats_transport.NatsTransport`
            (to see the matchers' consumers and the linker's status).
        folder: where the databases go.
        setup: the run (default: :class:`LiveCitySetup`'s).
        report: called with a line of progress.
    """
    setup = setup or LiveCitySetup()
    from cblrs.runtime.transport.topics import linker_status_topic
    from cblrs.runtime.wire import decode_status

    say = report or (lambda _line: None)
    started = time.monotonic()
    planes = sorted(city.scenes.planes)
    databases = {plane: folder / f"plane{plane}-host-a.db" for plane in planes}
    statuses: list[str] = []
    probe.subscribe(
        linker_status_topic("linker"),
        lambda delivery: statuses.append(decode_status(delivery.payload).state),
    )
    run = LiveCityRun(city, 0.0, databases, folder / "linker.db")
    # A cluster accepts clients before it has elected its JetStream leader; a matcher that
    # asks for its lease then is refused ("no response from stream").
    wait_for(lambda: _jetstream_ready(probe), setup.timeout_s, "JetStream on the cluster")
    matchers = {
        plane: start_matcher(city, url, plane, databases[plane], f"host-a{plane}", setup)
        for plane in planes
    }
    processes = list(matchers.values())
    try:
        for plane in planes:
            _wait_for_service(
                lambda plane=plane: (
                    _consumer_ready(probe, plane) or matchers[plane].poll() is not None
                ),
                setup.timeout_s,
                f"plane {plane}'s matcher",
                _log_of(databases[plane]),
            )
            _ended(matchers[plane], f"plane {plane}'s matcher", _log_of(databases[plane]))
        # The linker starts once the matchers are up: its --idle-exit counts from its start,
        # and four matchers starting on a loaded machine took longer than that (it ended
        # before the first track update). It reads the planes' streams from their start.
        linker = start_linker(city, url, run.linker_database, setup)
        processes.append(linker)
        _wait_for_service(
            lambda: "online" in statuses or linker.poll() is not None,
            setup.timeout_s,
            "the linker",
            _log_of(run.linker_database),
        )
        _ended(linker, "the linker", _log_of(run.linker_database))
        run.epoch = time.time() + 2.0
        threads, flushed = start_cameras(city, url, run.epoch, setup.speed)
        say(f"{len(threads)} cameras started, {len(planes)} matchers and the linker up")
        if setup.kill_plane is not None:
            plane = setup.kill_plane
            scene = city.scenes.planes[plane]
            share = int(setup.kill_share * len(scene.frames) * len(scene.cameras))
            _wait_for_service(
                lambda: store_counter(databases[plane], "processed") >= share,
                setup.timeout_s,
                f"plane {plane}'s matcher to track {share} messages",
                _log_of(databases[plane]),
            )
            matchers[plane].send_signal(signal.SIGKILL)
            matchers[plane].wait(30)
            killed = time.monotonic()
            run.killed_plane = plane
            run.processed_at_kill = store_counter(databases[plane], "processed")
            replacement = folder / f"plane{plane}-host-b.db"
            matchers[plane] = start_matcher(
                city, url, plane, replacement, f"host-b{plane}", setup, "--lease-wait", "60"
            )
            processes.append(matchers[plane])
            databases[plane] = replacement
            say(f"plane {plane}'s matcher killed after {run.processed_at_kill} messages")
            _wait_for_service(
                lambda: (
                    store_counter(replacement, "processed") >= run.processed_at_kill
                    or matchers[plane].poll() is not None
                ),
                setup.timeout_s,
                "the new host to re-track what the old one had",
                _log_of(replacement),
            )
            _ended(matchers[plane], f"plane {plane}'s new host", _log_of(replacement))
            run.recover_s = time.monotonic() - killed
            say(f"plane {plane} taken over in {run.recover_s:.1f} s")
        for thread in threads:
            thread.join(setup.timeout_s)
        run.cameras_flushed = len(flushed) == city.scenes.camera_count and all(flushed)
        for plane, process in matchers.items():
            out, _ = process.communicate(timeout=setup.timeout_s)
            if process.returncode != 0:
                raise RuntimeError(
                    f"plane {plane}'s matcher failed: {_log_tail(_log_of(databases[plane]))}"
                )
            run.matcher_summaries[plane] = json.loads(out)
        out, _ = linker.communicate(timeout=setup.timeout_s)
        if linker.returncode != 0:
            raise RuntimeError(f"the linker failed: {_log_tail(_log_of(run.linker_database))}")
        run.linker_summary = json.loads(out)
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
    run.seconds = time.monotonic() - started
    return run


def stored_tracks(run: LiveCityRun) -> dict[int, Tracks]:
    """Every plane's tracks in its final matcher database."""
    from cblrs.runtime.matcher.store import RuntimeStore

    tracks = {}
    for plane, database in run.databases.items():
        with RuntimeStore(database, read_only=True) as store:
            tracks[plane] = store.tracks()
    return tracks


def lost_messages(run: LiveCityRun) -> dict[int, int]:
    """Plane -> (camera, sequence) pairs its final database does not hold."""
    from cblrs.runtime.matcher.store import RuntimeStore

    lost = {}
    for plane, database in run.databases.items():
        scene = run.city.scenes.planes[plane]
        with RuntimeStore(database, read_only=True) as store:
            keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        lost[plane] = sum(
            (name, sequence) not in keys
            for name in scene.camera_names
            for sequence in range(len(scene.frames))
        )
    return lost


def live_city_figures(run: LiveCityRun) -> dict[str, Any]:
    """The run's figures: messages lost, whether the linker equals the offline link of the
    stored tracks, and the scores of ``cblrs experiment planes`` on the live tracks."""
    from cblrs.runtime.outputs.analytics_store import read_od
    from cblrs.runtime.outputs.linker_store import LinkerStore

    scenes = run.city.scenes
    spec = scenes.spec
    stored = stored_tracks(run)
    offline, handovers, _ = link_tracks(spec.planes, spec.links, stored)
    with LinkerStore(run.linker_database, read_only=True) as store:
        live = store.rows().tracks
        live_handovers = store.handovers()
        live_od = read_od(store)
        late_rows = store.counters().get("late_rows", 0)
    config = site_analytics_config(spec.links)
    counted = analyse_tracks(offline.tracks, spec.places, config)
    offline_od = {
        (origin, destination): value
        for origin, row in counted.od.items()
        for destination, value in row.items()
        if value
    }
    same_rows = len(live) == len(offline.tracks) and all(
        np.array_equal(getattr(live, name), getattr(offline.tracks, name))
        for name in ("frame", "timestamp", "track_id", "world_xy", "class_id")
    )
    # Scored on the city's own clock, as the ground truth is.
    linked = replace(live, timestamp=scenes.timestamps[live.frame])
    single = {
        plane: (
            scenes.planes[plane].ground_truth,
            replace(tracks, timestamp=scenes.timestamps[tracks.frame]),
        )
        for plane, tracks in stored.items()
    }
    single_idf1 = pooled_idf1(single)
    scores = evaluate(scenes.ground_truth, linked)
    truth_counts = analyse_tracks(scenes.ground_truth, spec.places, config)
    errors = count_errors(truth_counts, analyse_tracks(linked, spec.places, config))
    kinds: dict[str, int] = {}
    for item in handovers:
        kinds[item.kind] = kinds.get(item.kind, 0) + 1
    lost = lost_messages(run)
    return {
        "planes": len(scenes.planes),
        "cameras": scenes.camera_count,
        "objects": len(spec.world.objects),
        "trips": len(spec.trips),
        "frames": len(scenes.timestamps),
        "messages": len(scenes.timestamps) * scenes.camera_count,
        "lost": sum(lost.values()),
        "cameras_flushed": run.cameras_flushed,
        "processed": {
            plane: summary.get("processed") for plane, summary in run.matcher_summaries.items()
        },
        "killed_plane": run.killed_plane,
        "processed_at_kill": run.processed_at_kill,
        "recover_s": None if run.recover_s is None else round(run.recover_s, 2),
        "linker_updates": run.linker_summary.get("updates"),
        "linker_duplicates": run.linker_summary.get("duplicates", 0),
        "linker_late_rows": late_rows,
        "linker_equals_offline": same_rows
        and live_handovers == handovers
        and live_od == offline_od,
        "handovers": kinds,
        "single_plane_idf1": round(single_idf1, 2),
        "linked_idf1": round(float(scores.IDF1), 2),
        "ratio": round(float(scores.IDF1) / single_idf1, 4) if single_idf1 > 0 else None,
        "ids_linked": scores.num_predicted_ids,
        "ids_true": scores.num_gt_ids,
        "od_trips": sum(live_od.values()),
        "od_error": errors["od_error"],
        "seconds": round(run.seconds, 1),
    }
