"""The matcher service's metrics, live summary and events, scraped and received as a user
would: over HTTP from /metrics, /healthz, /readyz, and as messages on the plane's topics."""

from __future__ import annotations

import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from waiting import wait_until

from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.places import CountingLine, Places, Zone
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.metrics import (
    MetricsServer,
    MetricsServerError,
    ServiceMetrics,
    parse_address,
)
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import read_events
from cblrs.runtime.outputs.events import decode_event, decode_live
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.topics import detections_topic, events_topic, live_topic, status_topic
from cblrs.runtime.wire import encode_message, encode_status

PLANE = 1
SIZE_M = 20.0
FRAMES = 60


def walker_message(camera: str, frame: int, timestamp: float) -> CameraMessage:
    """One person walking along y = 10 m from x = 2 m to 17 m at 2.5 m/s, seen by ``camera``."""
    x = 2.0 + 0.25 * frame
    colour = [round(x / SIZE_M * 65535), round(10.0 / SIZE_M * 65535), PLANE]
    return CameraMessage(camera, frame, timestamp, frame, np.array([[100.0, 100, 140, 220]]),
                         np.array([0.9]), np.array([0]), np.array([colour]))


def scrape(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=5) as answer:
            return answer.status, answer.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.read().decode()


def metric(text: str, name: str) -> float:
    """The value of one exposition line ``name{...} value`` (the whole name with labels)."""
    for line in text.splitlines():
        if line.startswith(name + " ") or line == name:
            return float(line.rsplit(" ", 1)[1])
    raise AssertionError(f"{name} not in the metrics")


def test_metrics_live_summary_and_events(tmp_path):
    broker = InProcessBroker()
    places = Places(
        zones=(Zone("east", [[12.0, 5.0], [19.0, 5.0], [19.0, 15.0], [12.0, 15.0]]),),
        lines=(CountingLine("gate", (10.0, 2.0), (10.0, 18.0)),),
    )
    planes = PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), SIZE_M, SIZE_M)])
    metrics = ServiceMetrics(PLANE, ["A", "B"])
    store = RuntimeStore(tmp_path / "matcher.db")
    service = MatcherService(
        InProcessTransport(broker, "matcher"), store,
        make_matcher("fusion", planes, ["A", "B"]), PLANE, ["A", "B"], window_s=1.0,
        analytics=OnlineAnalytics(places), metrics=metrics, live_interval_s=0.2,
    )
    server = MetricsServer(("127.0.0.1", 0), metrics.exposition, service.health, service.ready)
    server.start()
    code, body = scrape(f"{server.url}/readyz")
    assert code == 503 and "starting" in body
    service.start()
    viewer = InProcessTransport(broker, "viewer", persistent=False)
    events: list = []
    lives: list = []
    viewer.subscribe(events_topic(PLANE), lambda d: (events.append(decode_event(d.payload)),
                                                     d.ack()))
    viewer.subscribe(live_topic(PLANE), lambda d: (lives.append(decode_live(d.payload)),
                                                   d.ack()))
    viewer.connect()
    camera = InProcessTransport(broker, "cameras", persistent=False)
    camera.connect()
    start = time.time() - 100.0
    for name in ("A", "B"):
        # What `cblrs camera` does when it starts: clear a retained message (issue 21: the
        # dashboard showed this as one rejected message per camera).
        camera.publish(detections_topic(PLANE, name), b"", retain=True)
    for frame in range(FRAMES):
        for name in ("A", "B"):
            payload = encode_message(walker_message(name, frame, start + 0.1 * frame), PLANE)
            camera.publish(detections_topic(PLANE, name), payload)
    camera.publish(detections_topic(PLANE, "A"), b'{"schema": "cblrs.detections/9"}')
    camera.publish(detections_topic(PLANE, "B"),
                   encode_message(walker_message("B", 0, start), PLANE))  # a duplicate
    for name in ("A", "B"):
        camera.publish(status_topic(PLANE, name),
                       encode_status(name, "offline", timestamp=time.time()))
    wait_until(lambda: store.counters().get("processed", 0) == 2 * FRAMES, 30, "tracking")
    wait_until(lambda: any(event.kind == "zone_entered" for event in events), 30, "events")
    wait_until(lambda: lives and lives[-1].lines[0].negative + lives[-1].lines[0].positive == 1
               and lives[-1].zones[0].entries == 1, 30,
               "a live summary with the crossing and the entry")

    labels = '{plane="1"}'
    # The collector observes a group after its commit (what "processed" counts): wait for it.
    wait_until(lambda: metric(scrape(f"{server.url}/metrics")[1],
                              f"cblrs_capture_to_track_seconds_count{labels}") == FRAMES, 30,
               "every group's capture-to-track time")
    code, text = scrape(f"{server.url}/metrics")
    assert code == 200
    assert metric(text, f"cblrs_messages_received_total{labels}") == 2 * FRAMES + 2
    assert metric(text, 'cblrs_messages_rejected_total{plane="1",reason="wrong_schema"}') == 1
    assert metric(text, f"cblrs_messages_duplicate_total{labels}") == 1
    assert metric(text, f"cblrs_messages_late_total{labels}") == 0
    assert metric(text, f"cblrs_capture_to_track_seconds_count{labels}") == FRAMES
    # Capture times were 100 s ago: every group is in the 10 s bucket's complement.
    assert metric(text, 'cblrs_capture_to_track_seconds_bucket{le="10.0",plane="1"}') == 0
    assert metric(text, 'cblrs_stage_duration_seconds_count{plane="1",stage="track"}') == FRAMES
    assert metric(text, 'cblrs_stage_duration_seconds_count{plane="1",stage="analytics"}') \
        == FRAMES
    assert metric(text, 'cblrs_stage_duration_seconds_count{plane="1",stage="commit"}') >= 1
    assert metric(text, f"cblrs_live_tracks{labels}") == 1
    assert metric(text, f"cblrs_tracker_lag_seconds{labels}") > 90
    assert abs(metric(text, 'cblrs_camera_last_seen_timestamp_seconds{camera="A",plane="1"}')
               - time.time()) < 30
    assert metric(text, 'cblrs_camera_messages_total{camera="A",plane="1"}') == FRAMES + 1
    assert metric(text, 'cblrs_events_total{kind="line_crossed",plane="1"}') == 1
    assert metric(text, 'cblrs_line_crossings{direction="negative",line="gate",plane="1"}') == 1
    assert scrape(f"{server.url}/healthz") == (200, "ok\n")
    assert scrape(f"{server.url}/readyz") == (200, "ok\n")
    assert scrape(f"{server.url}/nothing")[0] == 404

    live = lives[-1]
    cameras = {row.camera: row for row in live.cameras}
    assert cameras["A"].received == FRAMES + 1 and cameras["A"].rejected == 1
    assert cameras["B"].received == FRAMES + 1 and cameras["B"].rejected == 0
    assert live.zones[0].zone == "east" and live.zones[0].entries == 1

    service.close(flush=True)  # the stream ended: the visit ends, its event goes out
    left = [event for event in events if event.kind == "zone_left"]
    assert len(left) == 1 and left[0].exited is False and left[0].dwell_s > 1.0
    kinds = sorted(event.kind for event in events)
    assert kinds == ["line_crossed", "zone_entered", "zone_left"]
    assert all(event.published for event in read_events(store))
    assert scrape(f"{server.url}/healthz")[0] == 200
    server.close()
    store.close()


def test_a_failed_service_is_unhealthy(tmp_path):
    broker = InProcessBroker()
    planes = PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), SIZE_M, SIZE_M)])
    store = RuntimeStore(tmp_path / "matcher.db")
    service = MatcherService(InProcessTransport(broker, "matcher"), store,
                             make_matcher("fusion", planes, ["A"]), PLANE, ["A"])
    service.start()
    service._fail(RuntimeError("the disk is gone"), "test")
    healthy, reason = service.health()
    assert not healthy and "the disk is gone" in reason
    assert service.ready()[0] is False
    with pytest.raises(RuntimeError):
        service.close()
    store.close()


@pytest.mark.parametrize("text", ["9100", "host:port", "127.0.0.1:99999"])
def test_bad_metrics_addresses_say_so(text):
    with pytest.raises(MetricsServerError, match="HOST:PORT"):
        parse_address(text)


def test_metrics_address_in_use_says_so():
    first = MetricsServer(("127.0.0.1", 0), lambda: b"", lambda: (True, ""), lambda: (True, ""))
    with pytest.raises(MetricsServerError, match="cannot serve metrics on"):
        MetricsServer(("127.0.0.1", first.port), lambda: b"", lambda: (True, ""),
                      lambda: (True, ""))
    first.close()


def test_a_database_counted_with_other_places_is_refused_at_start(tmp_path):
    from cblrs.analytics import AnalyticsError

    planes = PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), SIZE_M, SIZE_M)])
    first = Places(lines=(CountingLine("gate", (10.0, 2.0), (10.0, 18.0)),))
    store = RuntimeStore(tmp_path / "matcher.db")
    online = OnlineAnalytics(first)
    online.update(walker_tracks(), 1.0)
    store.commit_group([], walker_tracks(), None, 1.0, {}, also=online.take_writes())
    moved = Places(lines=(CountingLine("gate", (11.0, 2.0), (11.0, 18.0)),))
    service = MatcherService(InProcessTransport(InProcessBroker(), "matcher"), store,
                             make_matcher("fusion", planes, ["A"]), PLANE, ["A"],
                             analytics=OnlineAnalytics(moved))
    with pytest.raises(AnalyticsError, match="for other places"):
        service.start()
    store.close()


def walker_tracks():
    from cblrs.detections import Tracks

    return Tracks(np.array([0]), np.array([1.0]), np.array([1]), np.array([[2.0, 10.0]]))
