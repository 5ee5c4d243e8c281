"""Retention of the matcher's database (issue 10, item 15): by age and by size, on by
default, never a message that is not yet tracked, open to other tables."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from test_runtime_store import entry

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.runtime.matcher.retention import (
    DEFAULT_TABLES,
    RetainedTable,
    RetentionPolicy,
    apply_retention,
)
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_schema import LATE, PENDING, PROCESSED

NOW = 1_800_000_000.0
HOUR = 3600.0


def _tracks(timestamps) -> Tracks:
    count = len(timestamps)
    return Tracks(
        frame=np.arange(count), timestamp=np.asarray(timestamps, float),
        track_id=np.arange(count), world_xy=np.zeros((count, 2)),
    )


def _fill(store: RuntimeStore, hours_ago: list[float], status: str, camera: str = "A") -> None:
    rows = [(entry(camera, index, NOW - hours * HOUR), status, NOW)
            for index, hours in enumerate(hours_ago)]
    store.insert_messages(rows)


def _inbox(store: RuntimeStore) -> list[tuple[str, float]]:
    return sorted((item.status, round((NOW - item.message.timestamp) / HOUR, 3))
                  for item in store.messages())


def test_the_default_policy_is_on():
    policy = RetentionPolicy()
    assert policy.enabled and (policy.max_age_s, policy.max_bytes) == (24 * HOUR, 4 * 2**30)
    assert policy.tables == DEFAULT_TABLES


def test_age_deletes_old_tracked_rows_and_keeps_what_is_not_tracked(tmp_path):
    with RuntimeStore(tmp_path / "m.db") as store:
        _fill(store, [30, 2], PROCESSED, camera="A")
        _fill(store, [30], LATE, camera="B")
        _fill(store, [30, 2], PENDING, camera="C")
        store.commit_group([], _tracks([NOW - 30 * HOUR, NOW - 2 * HOUR]), None, NOW)
        deleted = apply_retention(store, RetentionPolicy(max_age_s=24 * HOUR, max_bytes=None),
                                  NOW)
        assert deleted == {"inbox": 2, "tracks": 1}
        assert _inbox(store) == [(PENDING, 2.0), (PENDING, 30.0), (PROCESSED, 2.0)]
        assert store.tracks().timestamp.tolist() == [NOW - 2 * HOUR]
        # Nothing more to do: a second pass deletes nothing.
        assert sum(apply_retention(store, RetentionPolicy(max_bytes=None), NOW).values()) == 0


def test_size_deletes_the_oldest_first_but_never_pending_rows(tmp_path, caplog):
    with RuntimeStore(tmp_path / "m.db") as store:
        _fill(store, [float(hours) for hours in range(3000, 0, -1)], PROCESSED, camera="A")
        _fill(store, [1.0] * 300, PENDING, camera="P")
        before = store.used_bytes()
        limit = before // 2
        policy = RetentionPolicy(max_age_s=None, max_bytes=limit, batch_rows=200)
        deleted = apply_retention(store, policy, NOW)
        assert store.used_bytes() <= limit
        remaining = store.messages(PROCESSED)
        assert deleted["inbox"] == 3000 - len(remaining) > 0
        ages = [(NOW - item.message.timestamp) / HOUR for item in remaining]
        assert max(ages) < 3000 - deleted["inbox"] + 1, "the oldest must go first"
        assert store.status_counts()[PENDING] == 300
        # A bound below what is not yet tracked: nothing pending goes, and it says so.
        with caplog.at_level(logging.WARNING, logger="cblrs.runtime.matcher.retention"):
            apply_retention(store, RetentionPolicy(max_age_s=None, max_bytes=4096), NOW)
        assert store.status_counts() == {PENDING: 300}
        assert "is not yet tracked (kept)" in caplog.text


def test_other_tables_join_the_policy(tmp_path):
    with RuntimeStore(tmp_path / "m.db") as store:
        store.execute_write("CREATE TABLE visits_log (timestamp REAL NOT NULL, kind TEXT)")
        for hours in (48.0, 1.0):
            store.execute_write("INSERT INTO visits_log VALUES (?, 'zone_entry')",
                                (NOW - hours * HOUR,))
        policy = RetentionPolicy(
            max_bytes=None,
            tables=(*DEFAULT_TABLES, RetainedTable("visits_log", "timestamp"),
                    RetainedTable("not_there_yet", "timestamp")),
        )
        assert apply_retention(store, policy, NOW) == {"visits_log": 1}
        assert store.execute_write("DELETE FROM visits_log WHERE timestamp > 0") == 1


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"max_age_s": -1}, "retention age must be a positive number"),
        ({"max_age_s": float("nan")}, "retention age must be a positive number"),
        ({"max_bytes": 0}, "retention size must be positive"),
    ],
)
def test_bad_policies_are_refused(options, message):
    with pytest.raises(CblrsError, match=message):
        RetentionPolicy(**options)
    with pytest.raises(CblrsError, match="must be identifiers"):
        RetainedTable("inbox; DROP TABLE x", "timestamp")


def test_the_service_applies_retention_while_it_runs(tmp_path):
    from test_runtime_reliability import good_message

    from cblrs.matching import make_matcher
    from cblrs.plane import PlaneSet, PlaneSpec
    from cblrs.runtime.matcher.matcher_service import MatcherService
    from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
    from cblrs.runtime.transport.topics import detections_topic
    from cblrs.runtime.wire import encode_message

    broker = InProcessBroker()
    store = RuntimeStore(tmp_path / "m.db")
    service = MatcherService(
        InProcessTransport(broker, "matcher"), store,
        make_matcher("fusion", PlaneSet([PlaneSpec(1, (0.0, 0.0), 20.0, 20.0)]), ["CVLab1"]),
        1, ["CVLab1"], window_s=0.1,
        retention=RetentionPolicy(max_age_s=600.0, max_bytes=None, interval_s=0.2),
    )
    service.start()
    camera = InProcessTransport(broker, "camera", persistent=False)
    camera.connect()
    now = time.time()
    for sequence, age in enumerate((3600.0, 1800.0, 10.0)):  # accepted: younger than a day
        camera.publish(detections_topic(1, "CVLab1"),
                       encode_message(good_message("CVLab1", sequence, now - age), 1))
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and len(store.messages()) != 1:
        time.sleep(0.05)
    service.close(flush=True)
    assert [item.message.sequence for item in store.messages()] == [2]
    assert store.counters()["processed"] == 3
    store.close()


def test_rate_limited_log_says_how_many_it_held_back(caplog):
    from cblrs.runtime.transport.rate_limited import RateLimitedLog

    now = [0.0]
    log = RateLimitedLog(logging.getLogger("cblrs.test.rate"), interval_s=10, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="cblrs.test.rate"):
        assert log.log(logging.WARNING, "too_old", "rejected %s", "a")
        assert not log.log(logging.WARNING, "too_old", "rejected %s", "b")
        assert log.log(logging.WARNING, "in_future", "rejected %s", "c")  # its own key
        now[0] = 10.0
        assert log.log(logging.WARNING, "too_old", "rejected %s", "d")
    assert [record.getMessage() for record in caplog.records] == [
        "rejected a", "rejected c",
        "rejected d (and 1 more like it in the last 10 s)",
    ]
