"""Analytics on a site's local clock: hour and day bins on the daylight-saving days of
Europe/Zurich (2026-03-29: 23 hours, 2026-10-25: 25 hours), local ISO times in the tables,
counting within opening hours, and `cblrs analytics --start` end to end."""

from __future__ import annotations

import csv
import json
from datetime import datetime, timedelta
from zoneinfo import ZoneInfo

import numpy as np
import pytest
import yaml

from cblrs.analytics import Analytics, AnalyticsConfig, AnalyticsError, analyse_tracks
from cblrs.analytics.tables import result_of
from cblrs.cli.main import main
from cblrs.datasets import write_tracks
from cblrs.detections import Tracks
from cblrs.places import CountingLine, Places, Zone
from cblrs.runtime.outputs.events import decode_event, encode_event
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics

ZURICH = ZoneInfo("Europe/Zurich")
GATE = Places(lines=(CountingLine("gate", (0, -5), (0, 5)),))
HOURS = {"mon-fri": "07:00-19:00", "sat": "09:00-17:00", "sun": "closed"}


def local(*parts: int) -> float:
    """Epoch seconds of a Zurich wall-clock time (the first of a repeated hour)."""
    return datetime(*parts, tzinfo=ZURICH).timestamp()


def walkers(crossings: list[float], first_id: int = 1) -> Tracks:
    """One person per crossing time, walking along x through the gate at x = 0 at 1 m/s,
    seen once a second from 3 s before to 3 s after (so the crossing is exactly then)."""
    parts = []
    for index, moment in enumerate(crossings):
        seconds = moment + np.arange(-3.0, 4.0)
        parts.append(Tracks(np.arange(7), seconds, np.full(7, first_id + index),
                            np.c_[seconds - moment, np.zeros(7)]))
    tracks = Tracks.concatenate(parts)
    return tracks[np.argsort(tracks.timestamp, kind="stable")]


def every_minutes(start: float, end: float, minutes: int) -> list[float]:
    """Crossing times from ``start`` (epoch) every ``minutes``, offset by 1 min, before end."""
    return list(np.arange(start + 60.0, end, minutes * 60.0))


def hourly(day: tuple[int, int, int], *, interval_s: float = 3600.0, hours=None):
    begin = local(*day)
    next_day = datetime(*day) + timedelta(days=1)
    end = local(next_day.year, next_day.month, next_day.day)
    config = AnalyticsConfig(interval_s=interval_s, timezone="Europe/Zurich",
                             opening_hours=hours)
    result = analyse_tracks(walkers(every_minutes(begin, end, 10)), GATE, config)
    rows = [row for row in result.counts_over_time
            if row["place"] == "gate" and row["class"] == "unknown"]
    return begin, end, rows, result


def test_spring_forward_day_has_23_hour_bins_labelled_on_the_local_clock():
    begin, end, rows, result = hourly((2026, 3, 29))
    labels = [row["bin_start"] for row in rows]
    assert len(rows) == 23 == round((end - begin) / 3600)
    assert labels[:3] == ["2026-03-29T00:00:00+01:00", "2026-03-29T01:00:00+01:00",
                          "2026-03-29T03:00:00+02:00"]  # 02:00 never happened
    assert labels[-1] == "2026-03-29T23:00:00+02:00"
    assert all(row["bin_s"] == 3600 for row in rows)
    assert [row["count"] for row in rows] == [6] * 23  # a walker every 10 minutes
    assert sum(row["count"] for row in rows) == result.line_count("gate", "negative")


def test_fall_back_day_has_25_hour_bins_and_the_repeated_hour_twice():
    begin, end, rows, _ = hourly((2026, 10, 25))
    labels = [row["bin_start"] for row in rows]
    assert len(rows) == 25 == round((end - begin) / 3600)
    assert labels[2:4] == ["2026-10-25T02:00:00+02:00", "2026-10-25T02:00:00+01:00"]
    assert [row["bin_start_s"] for row in rows] == [begin + 3600 * hour for hour in range(25)]
    assert [row["count"] for row in rows] == [6] * 25


@pytest.mark.parametrize(("day", "hours"), [((2026, 3, 29), 23), ((2026, 10, 25), 25),
                                            ((2026, 6, 1), 24)])
def test_a_day_bin_is_the_local_calendar_day(day, hours):
    begin, end, rows, _ = hourly(day, interval_s=86400)
    assert [row["bin_start"][:10] for row in rows] == [f"{day[0]}-{day[1]:02d}-{day[2]:02d}"]
    assert rows[0]["bin_start_s"] == begin and rows[0]["bin_s"] == end - begin == hours * 3600
    assert rows[0]["count"] == 6 * hours


def test_occupancy_is_per_local_bin_and_its_length():
    zone = Places(zones=(Zone("hall", ((-1, -1), (1, -1), (1, 1), (-1, 1))),))
    start = local(2026, 10, 25, 1, 30)
    seconds = start + np.arange(0.0, 3 * 3600 + 1, 1.0)  # one person standing 3 hours
    tracks = Tracks(np.arange(len(seconds)), seconds, np.ones(len(seconds), int),
                    np.zeros((len(seconds), 2)))
    config = AnalyticsConfig(interval_s=3600, timezone="Europe/Zurich")
    result = analyse_tracks(tracks, zone, config)
    occupancy = {row["bin_start"][11:]: row["mean_occupancy"] for row in result.occupancy}
    # 01:30 CEST to 03:30 CET is three real hours over four local bins.
    assert occupancy == pytest.approx({"01:00:00+02:00": 0.5, "02:00:00+02:00": 1.0,
                                       "02:00:00+01:00": 1.0, "03:00:00+01:00": 0.5})


def test_opening_hours_gate_counts_and_a_crossing_at_closing_time_is_not_counted():
    day = (2026, 3, 27)  # a Friday: 07:00-19:00
    inside = [local(*day, 7, 0), local(*day, 12, 0), local(*day, 18, 59, 59)]
    outside = [local(*day, 6, 59, 59), local(*day, 19, 0), local(*day, 23, 0),
               local(2026, 3, 29, 12, 0)]  # Sunday: closed
    config = AnalyticsConfig(interval_s=3600, timezone="Europe/Zurich", opening_hours=HOURS)
    result = analyse_tracks(walkers(inside + outside), GATE, config)
    assert [crossing.timestamp for crossing in result.crossings] == inside
    assert result.line_count("gate", "negative") == 3
    assert result.summary["closed_events"] == 4
    always = analyse_tracks(walkers(inside + outside), GATE,
                            AnalyticsConfig(interval_s=3600, timezone="Europe/Zurich"))
    assert always.line_count("gate", "negative") == 7


def test_a_visit_begun_before_closing_counts_in_full_and_one_begun_after_does_not():
    zone = Places(zones=(Zone("shop", ((-2, -2), (2, -2), (2, 2), (-2, 2))),))
    config = AnalyticsConfig(interval_s=3600, timezone="Europe/Zurich", opening_hours=HOURS)
    parts = []
    for track, (enter, leave) in enumerate([((18, 50), (19, 20)), ((19, 5), (19, 30))], 1):
        first, last = local(2026, 3, 27, *enter), local(2026, 3, 27, *leave)
        seconds = np.arange(first - 10, last + 11, 2.0)
        x = np.where(seconds < first, -5.0, np.where(seconds > last, 5.0, 0.0))
        parts.append(Tracks(np.arange(len(seconds)), seconds, np.full(len(seconds), track),
                            np.c_[x, np.zeros(len(seconds))]))
    tracks = Tracks.concatenate(parts)
    result = analyse_tracks(tracks[np.argsort(tracks.timestamp, kind="stable")], zone, config)
    assert [(visit.track_id, round(visit.dwell_s / 60)) for visit in result.visits] == [(1, 30)]
    assert result.zone_row("shop")["entries"] == 1 and result.zone_row("shop")["exits"] == 1


def test_local_bins_do_not_depend_on_chunks_or_a_state_round_trip():
    crossings = every_minutes(local(2026, 10, 25, 0), local(2026, 10, 25, 6), 7)
    tracks = walkers(crossings)
    config = AnalyticsConfig(interval_s=900, timezone="Europe/Zurich", opening_hours=HOURS
                             | {"sun": "01:00-05:00"})
    whole = analyse_tracks(tracks, GATE, config)
    engine = Analytics(GATE, config)
    events = []
    for start in range(0, len(tracks), 5):
        events += engine.update(tracks[start:start + 5])
        saved = json.loads(json.dumps(engine.get_state()))
        engine = Analytics(GATE, config)
        engine.set_state(saved)
    events += engine.flush()
    assert result_of(engine, events).counts_over_time == whole.counts_over_time
    assert whole.summary["closed_events"] > 0 and whole.counts_over_time


def test_online_bins_are_keyed_by_their_local_start():
    config = AnalyticsConfig(interval_s=3600, timezone="Europe/Zurich")
    online = OnlineAnalytics(GATE, config, delay_s=0.0)
    crossing = local(2026, 10, 25, 2, 30) + 3600  # 02:30 CET, the second 02:00 hour
    events = online.update(walkers([crossing]), crossing + 10)
    events += online.flush()
    writes = online.take_writes()
    assert [key[0] for key in writes.bins] == [local(2026, 10, 25, 2) + 3600]
    body = json.loads(writes.events[0][5])
    assert body["time"] == "2026-10-25T02:30:00+01:00"
    assert decode_event(encode_event(body, 1, 1)).time == body["time"]  # on the wire too
    assert [event.kind for event in events] == ["line_crossed"]


@pytest.mark.parametrize(("settings", "words"), [
    ({"timezone": "Europe/Zurch"}, "unknown time zone 'Europe/Zurch'"),
    ({"timezone": "Europe/Zurich", "interval_s": 7.0}, "must divide a day"),
    ({"opening_hours": {"mon": "07:00-19:00"}}, "need the site's timezone"),
    ({"timezone": "UTC", "opening_hours": {"mon": "7-19"}}, "is not a range"),
])
def test_bad_local_settings_are_one_sentence(settings, words):
    with pytest.raises(AnalyticsError) as caught:
        AnalyticsConfig(**settings)
    message = str(caught.value)
    assert words in message and message.endswith(".") and "\n" not in message


def _site(tmp_path, **extra) -> str:
    site = {"version": 1, "name": "station", "timezone": "Europe/Zurich",
            "places": {"lines": [{"name": "gate", "start": [0, -5], "end": [0, 5]}]}, **extra}
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(site))
    return str(path)


def test_cli_start_puts_scene_seconds_on_the_local_clock(tmp_path, capsys):
    # Scene seconds from frame numbers at 1 fps; second 0 is 2026-03-29 00:00 local.
    begin = local(2026, 3, 29)
    crossings = [begin + offset for offset in (1800.0, 5400.0, 9000.0)]  # 00:30 01:30 03:30
    tracks = walkers(crossings)
    frames = np.round(tracks.timestamp - begin).astype(int)
    path = tmp_path / "tracks.txt"
    write_tracks(path, Tracks(frames, frames.astype(float), tracks.track_id, tracks.world_xy))
    out = tmp_path / "out"
    site = _site(tmp_path, opening_hours={"sun": "01:00-24:00"})
    assert main(["analytics", str(path), "--site", site, "--out", str(out), "--fps", "1",
                 "--start", "2026-03-29T00:00:00", "--interval", "3600", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["local_time"] == "Europe/Zurich" and summary["closed_events"] == 1
    with (out / "counts_over_time.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [row["bin_start"] for row in rows] == ["2026-03-29T01:00:00+01:00",
                                                  "2026-03-29T03:00:00+02:00"]
    assert [float(row["bin_start_s"]) for row in rows] == [begin + 3600, begin + 7200]
    with (out / "crossings.csv").open() as handle:
        times = [row["time"] for row in csv.DictReader(handle)]
    assert times == ["2026-03-29T01:30:00+01:00", "2026-03-29T03:30:00+02:00"]
    assert (out / "counts_over_time.png").stat().st_size > 10_000  # drawn on the local clock
    # Without --start the times are scene seconds: the zone is not applied, and it says so.
    assert main(["analytics", str(path), "--site", site, "--out", str(tmp_path / "scene"),
                 "--fps", "1", "--no-plots", "--json"]) == 0
    scene = json.loads(capsys.readouterr().out)
    assert scene["local_time"].startswith("not applied") and scene["closed_events"] == 0


def test_cli_bad_start_is_one_sentence(tmp_path, capsys):
    path = tmp_path / "tracks.txt"
    tracks = walkers([10.0])
    write_tracks(path, Tracks(tracks.frame, tracks.timestamp, tracks.track_id, tracks.world_xy))
    code = main(["analytics", str(path), "--site", _site(tmp_path), "--out",
                 str(tmp_path / "out"), "--fps", "1", "--start", "yesterday"])
    error = capsys.readouterr().err.strip()
    assert code != 0 and "--start: 'yesterday' is neither epoch seconds nor an ISO time" in error
    assert len(error.splitlines()) == 1
