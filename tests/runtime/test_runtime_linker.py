"""The linker service: planes' track updates in, global tracks and site counts out, equal to
the offline link of the same rows, through duplicates, bad updates and restarts."""

from __future__ import annotations

import math
import sqlite3
import time
from collections import Counter

import numpy as np
import pytest
from linker_corrections import (
    UNTIL,
    DirectDelivery,
    offline_link,
    run_correction,
    small_city,
    updates_of,
    wrong_then_corrected,
)
from waiting import wait_until

from cblrs.analytics.tables import analyse_tracks
from cblrs.detections import Tracks
from cblrs.linking.files import site_analytics_config
from cblrs.linking.linker import PlaneLinker, link_tracks
from cblrs.runtime.outputs.analytics_store import read_counts, read_od
from cblrs.runtime.outputs.linker_service import LinkerService
from cblrs.runtime.outputs.linker_store import LinkerStore, LinkerStoreError
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import events_topic, site_tracks_topic, tracks_topic
from cblrs.runtime.wire import decode_tracks, encode_tracks


@pytest.fixture(scope="module")
def city():
    """The small city's planes as matchers would publish them (:func:`small_city`)."""
    return small_city()


def client(broker, name, persistent=False):
    """A client of the in-process broker, or of a real Mosquitto (a RunningBroker)."""
    if isinstance(broker, InProcessBroker):
        return InProcessTransport(broker, name, persistent=persistent)
    return MqttTransport(name, broker.settings(), persistent=persistent)


def make_service(broker, scenes, database, **options):
    spec = scenes.spec
    transport = client(broker, "linker", persistent=True)
    analytics = OnlineAnalytics(spec.places, site_analytics_config(spec.links), delay_s=0.0)
    return LinkerService(transport, LinkerStore(database), PlaneLinker(spec.planes, spec.links),
                         spec.planes.ids, site={"planes": spec.planes.to_list()},
                         analytics=analytics, live_interval_s=None, **options)


@pytest.fixture(params=["inprocess", "mosquitto"])
def broker(request):
    if request.param == "inprocess":
        return InProcessBroker()
    return request.getfixturevalue("mosquitto")


def test_live_equals_offline_through_duplicates_bad_updates_and_a_restart(city, broker,
                                                                          tmp_path):
    scenes, per_plane = city
    viewer = client(broker, "viewer", persistent=True)
    seen: list = []
    events: list = []
    viewer.subscribe(site_tracks_topic(), lambda d: seen.append(decode_tracks(d.payload)))
    viewer.subscribe(events_topic(0), lambda d: events.append(d.payload))
    viewer.connect()
    matchers = {plane: client(broker, f"matcher{plane}") for plane in per_plane}
    for transport in matchers.values():
        transport.connect()
    database = tmp_path / "linker.db"
    service = make_service(broker, scenes, database)
    service.start()
    updates = updates_of(scenes, per_plane)
    half = len(updates) // 2
    for index, (_, plane, payload) in enumerate(updates[:half]):
        matchers[plane].publish(tracks_topic(plane), payload)
        if index % 97 == 0:  # a redelivery, and something that is not an update
            matchers[plane].publish(tracks_topic(plane), payload)
            matchers[plane].publish(tracks_topic(plane), b'{"schema": "cblrs.tracks/1"')
            matchers[plane].publish(tracks_topic(plane), encode_tracks(
                Tracks.empty(), plane, timestamp=time.time() + 3600.0))
    wait_until(lambda: service.stats().get("updates", 0) >= half, 30, "the first half")
    service.close()  # a stop, not the end: the next start resumes
    service.store.close()
    service = make_service(broker, scenes, database)
    service.start()
    for _, plane, payload in updates[half:]:
        matchers[plane].publish(tracks_topic(plane), payload)
    wait_until(lambda: service.stats().get("updates", 0) >= len(updates), 30, "every update")
    service.close(finish=True)
    store = service.store
    counters = store.counters()
    assert counters["updates"] == len(updates) and counters.get("late_rows", 0) == 0
    assert counters["duplicates"] >= half // 97 and counters["rejected.malformed_json"] >= 1
    assert counters["rejected.in_future"] == counters["rejected.malformed_json"]
    # The global rows equal the offline link of the same rows.
    offline, handovers, _ = link_tracks(scenes.spec.planes, scenes.spec.links, per_plane)
    live = store.rows()
    for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"):
        np.testing.assert_array_equal(getattr(live.tracks, name), getattr(offline.tracks, name))
    assert store.handovers() == handovers
    assert {item.kind for item in handovers} == {"overlap", "portal"}
    # ... and so do the site's counts.
    counted = analyse_tracks(offline.tracks, scenes.spec.places,
                             site_analytics_config(scenes.spec.links))
    od = read_od(store)
    assert sum(od.values()) >= 10
    assert od == {(origin, destination): value for origin, row in counted.od.items()
                  for destination, value in row.items() if value}
    counts = read_counts(store)
    assert sum(row["count"] for row in counted.lines if row["class"] == "all") >= 10
    for row in counted.lines:
        if row["class"] == "all":
            continue
        assert counts.get((row["line"], row["direction"], row["class"]), 0) == row["count"]
    for row in counted.zones:
        assert sum(value for (place, measure, _), value in counts.items()
                   if place == row["zone"] and measure == "entries") == row["entries"]
    # What a viewer got on cblrs/0/tracks is the stored rows (the first run's included).
    wait_until(lambda: sum(len(update.tracks) for update in seen) >= len(live), 10,
               "the published global rows")
    published = Tracks.concatenate([update.tracks for update in seen])
    keys = Counter(zip(published.timestamp.tolist(), published.track_id.tolist(), strict=True))
    assert keys == Counter(zip(live.tracks.timestamp.tolist(), live.tracks.track_id.tolist(),
                               strict=True))
    assert all(update.plane_id == 0 and update.source_plane is not None
               for update in seen if len(update.tracks))
    wait_until(lambda: len(events) >= sum(1 for _ in store.query("SELECT id FROM events")), 10,
               "the site's events")
    store.close()
    viewer.close()
    for transport in matchers.values():
        transport.close()


def test_a_silent_plane_is_waited_for_then_left_out(city, tmp_path):
    scenes, per_plane = city
    broker = InProcessBroker()
    now = [0.0]
    service = make_service(broker, scenes, tmp_path / "linker.db", max_wait_s=5.0,
                           monotonic=lambda: now[0])
    service.start()
    matchers = {plane: InProcessTransport(broker, f"m{plane}") for plane in per_plane}
    for transport in matchers.values():
        transport.connect()
    updates = [item for item in updates_of(scenes, per_plane) if item[1] != 4]
    for _, plane, payload in updates[:600]:
        matchers[plane].publish(tracks_topic(plane), payload)
    wait_until(lambda: service.stats().get("updates", 0) >= 600, 30, "the updates")
    assert service.stats().get("rows_out", 0) == 0  # plane 4 may still come
    now[0] = 6.0  # plane 4 never spoke: after max_wait_s the others go on without it
    for _, plane, payload in updates[600:650]:
        matchers[plane].publish(tracks_topic(plane), payload)
    wait_until(lambda: service.stats().get("rows_out", 0) > 0, 30, "rows without plane 4")
    # Plane 4's rows for times already linked are counted late, not linked.
    late = per_plane[4][per_plane[4].timestamp < service.linker.clock]
    assert len(late)
    matchers[4].publish(tracks_topic(4), encode_tracks(late, 4, timestamp=float(
        late.timestamp.max())))
    wait_until(lambda: service.stats().get("late_rows", 0) == len(late), 30, "late rows")
    service.close()
    service.store.close()


def test_the_database_is_held_private_and_bound_to_its_site(city, tmp_path):
    scenes, _ = city
    database = tmp_path / "linker.db"
    service = make_service(InProcessBroker(), scenes, database)
    service.start()
    assert database.stat().st_mode & 0o777 == 0o600
    second = LinkerStore(database)
    with pytest.raises(LinkerStoreError, match="in use by another linker"):
        second.hold()
    second.close()
    service.close()
    service.store.close()
    with LinkerStore(database) as store, pytest.raises(LinkerStoreError,
                                                       match="links another site"):
        store.bind({"planes": []})
    (tmp_path / "other.db").write_bytes(b"not sqlite at all")
    with pytest.raises(LinkerStoreError, match="is not a SQLite database"):
        LinkerStore(tmp_path / "other.db")
    connection = sqlite3.connect(tmp_path / "foreign.db")
    connection.execute("CREATE TABLE photos (id INTEGER)")
    connection.commit()
    connection.close()
    with pytest.raises(LinkerStoreError, match="not a cblrs linker database"):
        LinkerStore(tmp_path / "foreign.db")


def test_bad_settings_are_refused(city, tmp_path):
    scenes, _ = city
    with pytest.raises(ValueError, match="max_wait_s"):
        make_service(InProcessBroker(), scenes, tmp_path / "x.db", max_wait_s=math.nan)




def assert_rows_equal(live, offline):
    for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"):
        np.testing.assert_array_equal(getattr(live.tracks, name), getattr(offline.tracks, name))


@pytest.mark.parametrize("restart", [False, True], ids=["running", "restarted-midway"])
@pytest.mark.parametrize("seed", [1, 10, 11])
def test_a_correction_is_linked_whatever_batches_its_updates_come_in(city, tmp_path, seed,
                                                                     restart):
    """The deliveries of a batch are taken together (``_process``), and a broker interleaves
    the planes' matchers as it likes: whatever the batches, the rows are the offline link's,
    also when the linker stops and starts again during the correction. (These seeds lost
    plane 2's two rows at the linker's clock: a correction went back to a snapshot taken at
    its very time, which had linked that time without them.) While the correction is under
    way, plane 2 holds the watermark at its newest corrected time: the linker goes back once,
    not once per batch (34 to 40 times before). More seeds: ``linker_corrections.py``."""
    service, cost = run_correction(city, tmp_path, seed, restart=restart)
    try:
        offline, handovers = offline_link(city)
        assert_rows_equal(service.store.rows(), offline)
        assert service.store.handovers() == handovers
        assert cost["relinks"] == 1
    finally:
        service.store.close()


def test_a_correction_that_stops_does_not_hold_the_site(city, tmp_path):
    """A correction whose matcher dies halfway holds plane 2 at its newest corrected time
    only while the plane is waited for: silent for ``max_wait_s``, it is left out and the
    site goes on. A correction that stops short of the plane's clock (its last window ends
    earlier) is over once the plane sends its next update."""
    scenes, per_plane = city
    first, cut, corrected = wrong_then_corrected(scenes, per_plane)
    now = [0.0]
    service = make_service(InProcessBroker(), scenes, tmp_path / "linker.db", max_wait_s=5.0,
                           monotonic=lambda: now[0])
    service.start()

    def take(items):
        service._process([(DirectDelivery(tracks_topic(plane), payload), time.time())
                          for _, plane, payload in items])

    try:
        take(first[:cut])
        clock = service.linker.clock
        assert clock > UNTIL
        half = len(corrected) // 2
        take([(None, 2, payload) for payload in corrected[:half]])
        held = decode_tracks(corrected[half - 1]).timestamp
        others = [item for item in first[cut:] if item[1] != 2]
        take(others[:40])
        assert service.linker.clock < held  # plane 2's corrected rows still to come
        assert service.store.get_meta("correcting")["2"][1] == held
        now[0] = 6.0  # plane 2 silent for max_wait_s: left out
        take(others[40:80])
        assert service.linker.clock > clock
        # Its matcher back, it sends its next update: the correction is over.
        now[0] = 7.0
        take([item for item in first[cut:] if item[1] == 2][:1] + others[80:120])
        assert service.linker.clock > clock
        assert service._correcting[2][1] == service._correcting[2][2] == held
        assert service._plane_clock(2) == service._clocks[2] > held
        assert service.store.get_meta("correcting")["2"][2] == held
    finally:
        service.close()
        service.store.close()


@pytest.mark.parametrize("restart", [False, True], ids=["running", "restarted-midway"])
def test_a_planes_correction_is_linked_again_as_if_it_had_come_in_time(city, broker, tmp_path,
                                                                     restart):
    """Plane 2's matcher got messages late (:func:`wrong_then_corrected`); re-tracked, it
    publishes the right rows after the linker had linked the wrong ones. The
    linker's final rows, ids, hand-overs and counts are those of the right rows from the
    start (the offline link of them) — also when it stops halfway through the correction and
    starts again (the correction under way is in its file). It goes back once: plane 2
    holds the watermark while its corrected rows come (2 to 4 times before)."""
    scenes, per_plane = city
    first, cut, corrected = wrong_then_corrected(scenes, per_plane)
    assert first != updates_of(scenes, per_plane)
    # Not "viewer": that session (the first test's, on the module's broker) also holds a
    # subscription to the events, which this viewer would not acknowledge.
    viewer = client(broker, "viewer-of-corrections", persistent=True)
    corrected_seen: list = []
    viewer.subscribe(site_tracks_topic(), lambda delivery: corrected_seen.append(
        decode_tracks(delivery.payload).corrected_from))
    viewer.connect()
    matchers = {plane: client(broker, f"matcher{plane}") for plane in per_plane}
    for transport in matchers.values():
        transport.connect()
    service = make_service(broker, scenes, tmp_path / "linker.db")
    service.start()
    for _, plane, payload in first[:cut]:
        matchers[plane].publish(tracks_topic(plane), payload)
    wait_until(lambda: service.linker.clock > UNTIL, 30, "the wrong rows linked")
    assert len(service.store.rows())
    corrections = len(corrected)
    halfway = corrections // 2 if restart else corrections
    for payload in corrected[:halfway]:
        matchers[2].publish(tracks_topic(2), payload)
    if restart:
        wait_until(lambda: service.stats().get("corrections", 0) >= halfway, 30,
                   "half the correction")
        service.close()  # a stop, not the end
        service.store.close()
        service = make_service(broker, scenes, tmp_path / "linker.db")
        service.start()
    for payload in corrected[halfway:]:
        matchers[2].publish(tracks_topic(2), payload)
    for _, plane, payload in first[cut:]:
        matchers[plane].publish(tracks_topic(plane), payload)
    wait_until(lambda: service.stats().get("updates", 0) >= len(first)
               and service.stats().get("corrections", 0) >= corrections, 30, "every update")
    service.close(finish=True)
    store = service.store
    counters = store.counters()
    assert counters["relinks"] == 1 and counters.get("corrections_unlinked", 0) == 0
    assert counters["rows_linked_again"] > 0 and counters.get("late_rows", 0) == 0
    offline, handovers, _ = link_tracks(scenes.spec.planes, scenes.spec.links, per_plane)
    assert_rows_equal(store.rows(), offline)
    assert store.handovers() == handovers
    counted = analyse_tracks(offline.tracks, scenes.spec.places,
                             site_analytics_config(scenes.spec.links))
    assert read_od(store) == {(origin, destination): value
                              for origin, row in counted.od.items()
                              for destination, value in row.items() if value}
    counts = read_counts(store)
    for row in counted.lines:
        if row["class"] != "all":
            assert counts.get((row["line"], row["direction"], row["class"]), 0) == row["count"]
    wait_until(lambda: any(value is not None for value in corrected_seen), 10,
               "the global rows published again as a correction")
    store.close()
    viewer.close()
    for transport in matchers.values():
        transport.close()
