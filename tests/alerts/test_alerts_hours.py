"""Opening hours gate the places' alert rules: nothing fires while the site is closed, an
episode firing at closing time clears, a breach at opening waits its for_s afresh, and the
camera and matcher rules keep watching at night."""

from __future__ import annotations

from datetime import datetime
from zoneinfo import ZoneInfo

from cblrs.alerts import AlertEpisodes, Observation, load_alerts
from cblrs.localtime import LocalCalendar

CALENDAR = LocalCalendar.of("Europe/Zurich", {"mon-fri": "07:00-19:00"})
RULES = load_alerts({"rules": [
    {"name": "crowd", "kind": "occupancy", "zone": "hall", "above": 2, "for_s": 60},
    {"name": "rush", "kind": "line_count", "line": "gate", "above": 1, "per_s": 600},
    {"name": "camera down", "kind": "camera_offline", "camera": "cam1", "for_s": 0},
]})


def at(hour: int, minute: int = 0, day: int = 27) -> float:
    """Epoch seconds of Friday (27) or Saturday (28) March 2026, Zurich time."""
    return datetime(2026, 3, day, hour, minute, tzinfo=ZoneInfo("Europe/Zurich")).timestamp()


def crowd_states(episodes: AlertEpisodes, moments: list[float]) -> list[tuple[str, str]]:
    events = []
    for moment in moments:
        events += episodes.observe(Observation(moment, occupancy={"hall": 5},
                                               camera_silence_s={"cam1": 0.0}))
    return [(event.rule, event.state) for event in events]


def test_an_episode_firing_at_closing_time_clears_and_nothing_fires_while_closed():
    episodes = AlertEpisodes(RULES, CALENDAR)
    moments = [at(18, 57), at(18, 58), at(18, 59), at(19, 0), at(19, 1), at(23, 0)]
    events = []
    for moment in moments:
        events += [(event.state, CALENDAR.iso(event.timestamp)[11:16]) for event in
                   episodes.observe(Observation(moment, occupancy={"hall": 5},
                                                camera_silence_s={"cam1": 0.0}))]
    assert events == [("fired", "18:58"), ("cleared", "19:00")]


def test_a_breach_over_night_waits_its_hold_after_opening():
    episodes = AlertEpisodes(RULES, CALENDAR)
    assert crowd_states(episodes, [at(5, 0), at(6, 59), at(7, 0)]) == []
    assert crowd_states(episodes, [at(7, 1)]) == [("crowd", "fired")]
    # Saturday is closed all day (no hours given for it).
    assert crowd_states(AlertEpisodes(RULES, CALENDAR), [at(12, 0, 28), at(12, 5, 28)]) == []


def test_line_counts_are_quiet_when_closed_and_cameras_are_watched_at_night():
    episodes = AlertEpisodes(RULES, CALENDAR)
    crossings = (("gate", "positive", at(20, 0)), ("gate", "positive", at(20, 1)))
    night = episodes.observe(Observation(at(20, 2), crossings=crossings,
                                         camera_silence_s={"cam1": 60.0}))
    assert [(event.rule, event.state) for event in night] == [("camera down", "fired")]
    always = AlertEpisodes(RULES)
    fired = always.observe(Observation(at(20, 2), crossings=crossings,
                                       camera_silence_s={"cam1": 60.0}))
    assert {event.rule for event in fired} == {"rush", "camera down"}


def test_the_matcher_gates_its_alerts_and_counts_with_the_sites_hours(tmp_path):
    """The matcher's analytics take the site's zone and hours, and its alert service the
    same calendar (through MatcherService, from the analytics' settings)."""
    from argparse import Namespace

    import yaml

    from cblrs.cli.matcher import make_analytics
    from cblrs.runtime.matcher.store import RuntimeStore
    from cblrs.runtime.outputs.alert_service import AlertService
    from cblrs.runtime.outputs.analytics_service import CameraHealth
    from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
    from cblrs.site import load_site

    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump({
        "version": 1, "timezone": "Europe/Zurich", "opening_hours": {"mon-fri": "07:00-19:00"},
        "places": {"zones": [{"name": "hall", "polygon": [[0, 0], [4, 0], [4, 4], [0, 4]]}]}}))
    site = load_site(path)
    online = make_analytics(site, 1, Namespace(no_analytics=False, analytics_delay=0.5))
    calendar = online.engine.config.calendar
    assert calendar == CALENDAR

    class Plane:
        health = CameraHealth(["cam1"])

        def live_state(self):
            return {"clock": None, "occupancy": {"hall": 5}, "dwell": []}

    transport = InProcessTransport(InProcessBroker(), "matcher")
    transport.connect()
    clock = [at(20, 0)]
    with RuntimeStore(tmp_path / "m.db") as store:
        service = AlertService(transport, store, 1, ["cam1"], RULES, {}, Plane(),
                               lambda now: 0.0, interval_s=3600, wall_clock=lambda: clock[0],
                               calendar=calendar)
        service.start()
        fired = service.observe_once()  # 20:00 Friday: closed, the crowd alerts nothing
        clock[0] = at(10, 0, day=30)  # Monday 10:00, open: the crowd's for_s starts
        pending = service.observe_once()
        clock[0] += 60
        fired_open = service.observe_once()
        service.stop()
    assert (fired, pending, fired_open) == (1, 0, 1)  # the camera at night; the crowd by day
