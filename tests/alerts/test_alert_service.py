"""The matcher's alert service on a real store: what it observes of the plane (occupancy,
longest visit, crossings since the last observation, camera silence, lag), the alerts it
commits and publishes on ``cblrs/<plane>/alerts``, and the crossings it never counts twice
across a restart. The clock is the test's; the threads do not tick (``interval_s`` is long),
each observation is one ``observe_once``."""

from __future__ import annotations

import json
import time

import pytest

from cblrs.alerts import load_alerts
from cblrs.alerts.rules import AlertsError
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.alert_service import BACKBONE, AlertService, make_senders
from cblrs.runtime.outputs.analytics_service import CameraHealth
from cblrs.runtime.outputs.events import decode_alert
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.topics import alerts_topic

RULES = {"rules": [
    {"name": "crowd", "kind": "occupancy", "zone": "market", "above": 1, "for_s": 2},
    {"name": "loitering", "kind": "dwell", "zone": "market", "above_s": 60},
    {"name": "rush", "kind": "line_count", "line": "gate", "above": 2, "per_s": 10},
    {"name": "behind", "kind": "matcher_lag", "above_s": 5},
    {"name": "down", "kind": "camera_offline", "camera": "cam2", "for_s": 3},
]}


class Plane:
    """What the service reads: the tracker's live state, the cameras' health, the lag."""

    def __init__(self):
        self.live = {"clock": None, "occupancy": {}, "dwell": []}
        self.now_monotonic = 0.0
        self.health = CameraHealth(["cam1", "cam2"], monotonic=lambda: self.now_monotonic)
        self.lag_s = 0.0

    def live_state(self):
        return dict(self.live)


def crossing(store: RuntimeStore, track: int, direction: str = "positive") -> None:
    body = json.dumps({"kind": "line_crossed", "place": "gate", "direction": direction})
    store.execute_write(
        "INSERT INTO events (timestamp, kind, place, track_id, key, body) "
        "VALUES (0, 'line_crossed', 'gate', ?, ?, ?)", (track, f"k{track}", body))


@pytest.fixture
def setup(tmp_path):
    broker = InProcessBroker()
    transport = InProcessTransport(broker, "matcher")
    transport.connect()
    viewer = InProcessTransport(broker, "viewer")
    received = []
    viewer.subscribe(alerts_topic(1), lambda d: (received.append(decode_alert(d.payload)),
                                                d.ack()))
    viewer.connect()
    store = RuntimeStore(tmp_path / "m.db")
    plane = Plane()
    clock = [1000.0]

    def service():
        alerts = AlertService(transport, store, 1, ["cam1", "cam2"], load_alerts(RULES), {},
                              plane, lambda now: plane.lag_s, interval_s=3600,
                              wall_clock=lambda: clock[0])
        alerts.start()
        return alerts

    yield {"service": service, "plane": plane, "clock": clock, "store": store,
           "received": received}
    store.close()


def states(received, count=None):
    """The (episode, state) of the alerts received, once ``count`` have (the viewer's
    transport delivers on a thread of its own)."""
    deadline = time.monotonic() + 10
    while count is not None and len(received) < count and time.monotonic() < deadline:
        time.sleep(0.01)
    return [(alert.episode, alert.state) for alert in received]


def test_each_rule_is_observed_fired_published_and_cleared(setup):
    service, plane, clock, store = (setup[key] for key in ("service", "plane", "clock", "store"))
    alerts = service()
    plane.health.add("cam1", 1, 0, 999.0)
    plane.health.add("cam2", 1, 0, 999.0)
    plane.live = {"clock": 999.0, "occupancy": {"market": 3},
                  "dwell": [("market", 7, 12.0), ("market", 8, 75.0)]}
    for track in range(3):
        crossing(store, track)
    plane.lag_s = 9.0
    observation, seen = alerts.observation(clock[0])
    assert observation.occupancy == {"market": 3}
    assert observation.longest_visit_s == {"market": 75.0}
    assert [line for line, _, _ in observation.crossings] == ["gate"] * 3 and seen == 3
    assert observation.camera_silence_s == {"cam1": 0.0, "cam2": 0.0}
    assert observation.lag_s == 9.0
    assert alerts.observe_once() == 3  # dwell, line count, lag now; occupancy needs 2 s
    clock[0] += 2.5
    plane.now_monotonic += 2.5
    assert alerts.observe_once() == 1  # the crowd has held 2.5 s
    assert states(setup["received"], 4) == [  # in rule order, then in time
        ("loitering/market/1", "fired"), ("rush/gate/1", "fired"), ("behind/matcher/1", "fired"),
        ("crowd/market/1", "fired")]
    assert {item.episode for item in setup["received"][-1].active} == {
        "loitering/market/1", "rush/gate/1", "behind/matcher/1", "crowd/market/1"}
    # Everything clears: nobody inside, no crossing for 10 s, no lag; cam2 falls silent.
    plane.live = {"clock": 1002.0, "occupancy": {"market": 0}, "dwell": []}
    plane.lag_s = 0.0
    clock[0] += 10
    plane.now_monotonic += 10
    plane.health.add("cam1", 1, 0, 1010.0)
    assert alerts.observe_once() == 4
    clock[0] += 5
    plane.now_monotonic += 5
    assert alerts.observe_once() == 1  # cam2: silent for 15 s, offline for 5 > 3 s
    assert states(setup["received"], 9)[-1] == ("down/cam2/1", "fired")
    assert len(setup["received"]) == 9
    rows = store.query("SELECT delivered FROM alerts")
    assert len(rows) == 9 and all(json.loads(row[0]) == [BACKBONE] for row in rows)
    alerts.stop()


def test_a_restarted_service_counts_each_crossing_once(setup):
    service, clock, store = setup["service"], setup["clock"], setup["store"]
    alerts = service()
    crossing(store, 1)
    crossing(store, 2)
    assert alerts.observe_once() == 0  # two crossings in 10 s: not above 2
    alerts.stop()
    restarted = service()  # the same store: the crossings were committed as counted
    crossing(store, 3)
    clock[0] += 1
    observation, seen = restarted.observation(clock[0])
    assert len(observation.crossings) == 1 and seen == 3
    assert restarted.observe_once() == 1  # the window, restored, holds three now
    assert states(setup["received"], 1) == [("rush/gate/1", "fired")]
    restarted.stop()


def test_history_before_the_alerts_is_not_counted(setup):
    store = setup["store"]
    for track in range(5):
        crossing(store, track)
    alerts = setup["service"]()
    assert alerts.observe_once() == 0 and alerts.observation(setup["clock"][0])[0].crossings == ()
    alerts.stop()


def test_webhook_secrets_are_read_before_the_matcher_starts(tmp_path):
    hook = {"name": "ops", "url": "http://127.0.0.1:9/hook", "secret_env": "CBLRS_TEST_HOOK"}
    model = load_alerts({**RULES, "webhooks": [hook]})
    with pytest.raises(AlertsError, match="CBLRS_TEST_HOOK"):
        make_senders(model, tmp_path, environment={})
    assert list(make_senders(model, tmp_path, environment={"CBLRS_TEST_HOOK": "s"})) == ["ops"]
    reserved = load_alerts({**RULES, "webhooks": [{**hook, "name": BACKBONE}]})
    with pytest.raises(AlertsError, match="the broker's"):
        make_senders(reserved, tmp_path, environment={"CBLRS_TEST_HOOK": "s"})
