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
