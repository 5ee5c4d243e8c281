"""The matcher's SQLite store: inbox de-duplication, atomic groups, restart state, errors."""

from __future__ import annotations

import shutil
import sqlite3
import stat
import subprocess
import sys
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from waiting import wait_until

from cblrs.detections import CameraMessage, Tracks
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_file import (
    StoreError,
    StoreNotReady,
    WriterLock,
    checkpoint_regularly,
)
from cblrs.runtime.matcher.store_rows import InboxEntry
from cblrs.runtime.matcher.store_schema import _SCHEMA, LATE, PENDING, PROCESSED


def message(camera: str = "CVLab1", sequence: int = 0, timestamp: float = 10.0, count: int = 2):
    return CameraMessage(
        camera, sequence, timestamp, sequence * 5,
        xyxy=np.arange(4 * count, dtype=float).reshape(count, 4) + np.array([0, 0, 10, 10]),
        confidence=np.linspace(0.5, 1.0, count),
        class_id=np.zeros(count, np.int64),
        colour=np.arange(3 * count, dtype=np.int64).reshape(count, 3) + 1,
    )


def entry(*args, **kwargs) -> InboxEntry:
    return InboxEntry.from_message(message(*args, **kwargs))


def tracks(count: int, frame: int = 5) -> Tracks:
    return Tracks(
        frame=np.full(count, frame),
        timestamp=np.full(count, 10.0),
        track_id=np.arange(1, count + 1),
        world_xy=np.arange(2 * count, dtype=float).reshape(count, 2) / 3,
        camera_id=np.arange(count) % 2 - 1,
        xyxy=np.where(np.arange(count)[:, None] % 2 == 0, np.nan, 1.5 * np.ones((count, 4))),
    )


@pytest.fixture
def store(tmp_path):
    with RuntimeStore(tmp_path / "runtime.db") as opened:
        yield opened


def test_new_database_is_in_wal_mode(tmp_path):
    RuntimeStore(tmp_path / "a.db").close()
    connection = sqlite3.connect(tmp_path / "a.db")
    assert connection.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    connection.close()


def test_insert_deduplicates_by_camera_and_sequence_and_counts(store):
    first = store.insert_messages(
        [(entry("CVLab1", 0), PENDING, 1.0), (entry("CVLab2", 0), PENDING, 1.0),
         (entry("CVLab1", 0), PENDING, 1.0)],
        {"received": 3},
    )
    second = store.insert_messages(
        [(entry("CVLab1", 0), PENDING, 2.0), (entry("CVLab1", 1, 5.0), LATE, 2.0)],
        {"received": 2},
    )
    assert first == [True, True, False]
    assert second == [False, True]
    assert store.counters() == {"accepted": 3, "duplicates": 2, "late": 1, "received": 5}
    assert store.status_counts() == {PENDING: 2, LATE: 1}


def test_empty_insert_is_a_no_op(store):
    assert store.insert_messages([], {}) == []
    assert store.counters() == {}
    assert store.messages() == []
    assert len(store.tracks()) == 0


@pytest.mark.parametrize("count", [0, 1, 3])
def test_stored_messages_read_back_exactly(store, count):
    original = message("IDIAP1", 7, 1700000000.123456789, count)
    store.insert_messages([(InboxEntry.from_message(original), PENDING, 5.0)])
    (stored,) = store.messages(PENDING)
    back = stored.message
    assert (back.camera_id, back.sequence, back.timestamp, back.frame) == (
        "IDIAP1", 7, original.timestamp, original.frame
    )
    for name in ("xyxy", "confidence", "class_id", "colour"):
        np.testing.assert_array_equal(getattr(back, name), getattr(original, name))
        assert getattr(back, name).dtype == getattr(original, name).dtype


@pytest.mark.parametrize("count", [0, 1, 3])
def test_an_entry_rebuilds_the_message_a_checked_constructor_builds(count):
    """The tracker process's message of an entry (set without CameraMessage's checks) has the
    columns, shapes, dtypes and schema the checked constructor gives."""
    original = message("IDIAP1", 7, 12.5, count)
    rebuilt = InboxEntry.from_message(original).message()
    assert type(rebuilt) is CameraMessage
    for name in ("camera_id", "sequence", "timestamp", "frame", "schema"):
        assert getattr(rebuilt, name) == getattr(original, name)
        assert type(getattr(rebuilt, name)) is type(getattr(original, name))
    for name in ("xyxy", "confidence", "class_id", "colour"):
        assert getattr(rebuilt, name).shape == getattr(original, name).shape
        assert getattr(rebuilt, name).dtype == getattr(original, name).dtype
        np.testing.assert_array_equal(getattr(rebuilt, name), getattr(original, name))


@pytest.mark.parametrize("body", [
    '{"xyxy":[[0,0,1,1]],"confidence":[0.5,0.6],"class_id":[0],"colour":[[1,2,3]]}',
    '{"xyxy":[[0,0,1]],"confidence":[0.5],"class_id":[0],"colour":[[1,2,3]]}',
    '{"xyxy":[[0,0,1,1]],"confidence":[0.5],"class_id":[0],"colour":[[1,2]]}',
    '{"xyxy":[[0,0,1,1]],"confidence":[[0.5]],"class_id":[0],"colour":[[1,2,3]]}',
])
def test_an_entry_whose_columns_do_not_fit_is_refused(body):
    with pytest.raises(ValueError, match="columns of other shapes"):
        InboxEntry("IDIAP1", 7, 12.5, 3, body).message()


def test_commit_group_is_one_transaction_and_survives_reopening(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as store:
        store.insert_messages([(entry("CVLab1", 0), PENDING, 1.0),
                               (entry("CVLab2", 0), PENDING, 1.0),
                               (entry("CVLab1", 1, 11.0), PENDING, 1.0)])
        store.commit_group(
            [("CVLab1", 0), ("CVLab2", 0)], tracks(3), {"next_id": 4, "x": [1.5, np.nan]}, 10.0,
            {"processed": 2, "groups": 1},
        )
    with RuntimeStore(path) as store:
        assert store.status_counts() == {PROCESSED: 2, PENDING: 1}
        assert store.released_timestamp() == 10.0
        state = store.matcher_state()
        assert state["next_id"] == 4 and np.isnan(state["x"][1])
        assert store.counters()["processed"] == 2
        back = store.tracks()
        expected = tracks(3)
        for name in ("frame", "timestamp", "track_id", "world_xy", "camera_id", "xyxy"):
            np.testing.assert_array_equal(getattr(back, name), getattr(expected, name))
        (pending,) = store.messages(PENDING)
        assert (pending.message.camera_id, pending.message.sequence) == ("CVLab1", 1)


def test_commit_of_a_superseded_tracker_is_refused(store):
    store.insert_messages([(entry("CVLab1", 0), PENDING, 1.0)])
    first = store.claim()
    store.commit_group([], tracks(1), {"n": 1}, 9.0, {"groups": 1}, tracker=first)
    second = store.claim()  # a restarted service took over
    with pytest.raises(StoreError, match="taken over"):
        store.commit_group([("CVLab1", 0)], tracks(2), {"n": 2}, 10.0, {"groups": 1},
                           tracker=first)
    store.commit_group([("CVLab1", 0)], tracks(2), {"n": 2}, 10.0, {"groups": 1},
                       tracker=second)
    assert store.counters()["groups"] == 2
    assert len(store.tracks()) == 3
    assert store.matcher_state() == {"n": 2}


def test_shared_store_leaves_checkpoints_to_the_checkpoint_thread(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as store:
        shared = store.share()
        with RuntimeStore(shared.path, write_lock=shared.write_lock) as other:
            for connection in (store._connection, other._connection):
                assert connection.execute("PRAGMA wal_autocheckpoint").fetchone() == (0,)
            store.insert_messages([(entry("A", sequence), PENDING, 1.0) for sequence in range(500)])
            other.commit_group([("A", 0)], tracks(2), {"n": 1}, 10.0, {"groups": 1})
            before = path.stat().st_size  # the rows are still in the WAL only
            stop = threading.Event()
            thread = threading.Thread(target=checkpoint_regularly, args=(path, stop, 0.01))
            thread.start()
            try:
                wait_until(lambda: path.stat().st_size > before, 10, "a checkpoint")
            finally:
                stop.set()
                thread.join()
            assert other.status_counts() == {PROCESSED: 1, PENDING: 499}


def test_writer_lock_is_freed_when_its_holder_is_killed(tmp_path):
    path = tmp_path / "runtime.db-writers.lock"
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time; from cblrs.runtime.matcher.store import WriterLock; "
         "lock = WriterLock(sys.argv[1]); lock.acquire(); print('held', flush=True); "
         "time.sleep(60)", str(path)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        lock = WriterLock(path)
        acquired = threading.Event()
        waiter = threading.Thread(target=lambda: (lock.acquire(), acquired.set()), daemon=True)
        waiter.start()
        assert not acquired.wait(0.3), "the lock was not exclusive"
        holder.kill()  # in the middle of its "transaction"
        assert acquired.wait(10), "a dead holder kept the lock"
        lock.release()
        lock.close()
    finally:
        holder.kill()
        holder.wait()


def test_failed_group_commit_leaves_nothing_behind(store):
    store.insert_messages([(entry("CVLab1", 0), PENDING, 1.0)])
    with pytest.raises(TypeError, match="cannot store object"):
        store.commit_group([("CVLab1", 0)], tracks(2), {"bad": object()}, 10.0, {"processed": 1})
    assert store.status_counts() == {PENDING: 1}
    assert len(store.tracks()) == 0
    assert store.released_timestamp() is None
    assert "processed" not in store.counters()


def test_bind_refuses_a_database_of_another_matcher(store):
    store.bind({"plane_id": 1, "camera_ids": ["a", "b"]})
    store.bind({"plane_id": 1, "camera_ids": ["a", "b"]})
    with pytest.raises(StoreError, match=r"plane_id=1, not 2; use another --db"):
        store.bind({"plane_id": 2, "camera_ids": ["a", "b"]})


def _other_program(path):
    with sqlite3.connect(path) as connection:
        connection.execute("CREATE TABLE invoices (id INTEGER)")


@pytest.mark.parametrize("read_only", [False, True], ids=["writing", "reading"])
@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (lambda path: path.write_bytes(b""),
         r"is an empty file[,:] (not a cblrs matcher database|a matcher is still creating)"),
        (lambda path: path.write_bytes(b"this is not a database, just some text" * 20),
         r"is not a SQLite database \(a cblrs matcher database is one\)"),
        (_other_program, r"is a SQLite database of another program \(tables invoices\)"),
        (lambda path: path.mkdir(), r"is not a file"),
    ],
    ids=["empty", "text", "other program", "folder"],
)
def test_unusable_files_are_refused_in_one_sentence(tmp_path, make, expected, read_only):
    path = tmp_path / "runtime.db"
    make(path)
    with pytest.raises(StoreError, match=expected):
        RuntimeStore(path, read_only=read_only)


def test_missing_database_and_missing_folder(tmp_path):
    with pytest.raises(StoreError, match="does not exist"):
        RuntimeStore(tmp_path / "none.db", read_only=True)
    with pytest.raises(StoreError, match=r"the folder .*gone of the database m\.db does not exist"):
        RuntimeStore(tmp_path / "gone" / "m.db")
    assert not (tmp_path / "gone").exists(), "the folder must not be created silently"


def test_a_database_being_created_is_not_ready_for_readers(tmp_path):
    """Each state a starting matcher's file passes through tells a reader to try again."""
    path = tmp_path / "runtime.db"
    path.write_bytes(b"")  # created private, nothing written yet
    with pytest.raises(StoreNotReady, match="a matcher is still creating it"):
        RuntimeStore(path, read_only=True)
    with sqlite3.connect(path) as connection:  # WAL switched on, no table yet
        connection.execute("PRAGMA journal_mode=WAL")
    with pytest.raises(StoreNotReady, match="holds no matcher tables yet"):
        RuntimeStore(path, read_only=True)
    with sqlite3.connect(path) as connection:  # tables, no schema version yet
        connection.executescript(_SCHEMA)
    with pytest.raises(StoreNotReady, match="holds no matcher tables yet"):
        RuntimeStore(path, read_only=True)
    RuntimeStore(path).close()
    with RuntimeStore(path, read_only=True) as reader:
        assert reader.counters() == {}


def test_reading_databases_while_they_are_created_never_fails_otherwise(tmp_path):
    """A reader polling a starting matcher (the fault tests, ``--stats`` in a loop) sees the
    database either not ready or whole; it used to meet "no such table: counters"."""
    paths = [tmp_path / f"m{index}.db" for index in range(150)]
    done = threading.Event()
    outcomes: dict[str, int] = {}

    def create() -> None:
        for path in paths:
            RuntimeStore(path).close()
        done.set()

    writer = threading.Thread(target=create)
    writer.start()
    for path in paths:
        while True:
            if not path.exists():
                continue
            try:
                with RuntimeStore(path, read_only=True) as reader:
                    reader.counters()
            except StoreNotReady:
                outcomes["not ready"] = outcomes.get("not ready", 0) + 1
                continue
            outcomes["read"] = outcomes.get("read", 0) + 1
            break
    writer.join()
    assert done.is_set() and outcomes["read"] == len(paths), outcomes


def test_damaged_database_is_reported(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as store:
        store.insert_messages([(entry("A", index), PENDING, 1.0) for index in range(2000)])
    data = bytearray(path.read_bytes())
    data[4096:len(data) // 2] = b"\xff" * (len(data) // 2 - 4096)  # pages after the first
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match=r"(is damaged: SQLite says|not a usable SQLite)"):
        with RuntimeStore(path, read_only=True) as store:
            store.summary()


def test_database_files_are_private(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as store:
        store.add_counters({"received": 1})
        shared = store.share()
        store.add_counters({"received": 1})
        modes = {item.name: stat.S_IMODE(item.stat().st_mode) for item in tmp_path.iterdir()}
    assert shared.path == path
    assert modes == dict.fromkeys(modes, 0o600), modes
    assert {"runtime.db", "runtime.db-wal", "runtime.db-shm"} <= set(modes)


def test_a_deleted_database_fails_the_next_commit(tmp_path):
    folder = tmp_path / "db"
    folder.mkdir()
    with RuntimeStore(folder / "runtime.db") as store:
        store.insert_messages([(entry("A", 0), PENDING, 1.0)])
        shutil.rmtree(folder)
        with pytest.raises(StoreError, match="was deleted or replaced while the matcher"):
            store.insert_messages([(entry("A", 1), PENDING, 1.0)])


def test_a_replaced_database_fails_the_next_commit(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as store:
        store.add_counters({"received": 1})
        path.rename(tmp_path / "moved.db")
        RuntimeStore(path).close()  # someone creates a new, empty file under the old name
        with pytest.raises(StoreError, match="was deleted or replaced"):
            store.add_counters({"received": 1})


def test_a_held_database_refuses_a_second_matcher(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as first:
        first.hold()
        second = RuntimeStore(path)
        with pytest.raises(StoreError, match=r"is in use by another matcher \(pid \d+ on "):
            second.hold()
        second.close()
    with RuntimeStore(path) as third:  # released when the first closed
        third.hold()


def test_read_only_reader_sees_a_writer_commits(tmp_path):
    path = tmp_path / "runtime.db"
    with RuntimeStore(path) as writer:
        writer.add_counters({"received": 2})
        with RuntimeStore(path, read_only=True) as reader:
            assert reader.counters() == {"received": 2}
            writer.add_counters({"received": 3})
            assert reader.summary()["counters"] == {"received": 5}


@settings(max_examples=15, deadline=None)
@given(
    timestamp=st.floats(allow_nan=False, allow_infinity=False, width=64),
    sequence=st.integers(0, 2**53),
    colours=st.lists(st.tuples(*[st.integers(0, 65535)] * 3), max_size=5),
)
def test_message_round_trip_property(tmp_path_factory, timestamp, sequence, colours):
    count = len(colours)
    original = CameraMessage(
        "cam", sequence, timestamp, 0, np.zeros((count, 4)), np.ones(count),
        np.zeros(count, np.int64), np.array(colours, dtype=np.int64).reshape(count, 3),
    )
    with RuntimeStore(tmp_path_factory.mktemp("db") / "r.db") as store:
        store.insert_messages([(InboxEntry.from_message(original), PENDING, 0.0)])
        (back,) = store.messages()
    assert back.message.timestamp == timestamp
    assert back.message.sequence == sequence
    np.testing.assert_array_equal(back.message.colour, original.colour)


_EARLIER_INBOX = """
CREATE TABLE inbox (
    camera_id TEXT NOT NULL, sequence INTEGER NOT NULL, timestamp REAL NOT NULL,
    frame INTEGER NOT NULL, received_at REAL NOT NULL, status TEXT NOT NULL,
    body TEXT NOT NULL, PRIMARY KEY (camera_id, sequence)
) WITHOUT ROWID;
"""


@pytest.mark.parametrize("earlier", [False, True], ids=["rowid inbox", "WITHOUT ROWID inbox"])
def test_inbox_layouts_deduplicate_and_process_alike(tmp_path, earlier):
    path = tmp_path / "runtime.db"
    if earlier:  # a file written before the inbox became a rowid table
        with sqlite3.connect(path) as connection:
            connection.executescript(_EARLIER_INBOX)
    with RuntimeStore(path) as opened:
        first = [(entry("A", 0), PENDING, 1.0), (entry("B", 0), PENDING, 1.0)]
        assert opened.insert_messages(first) == [True, True]
        again = [(entry("A", 0), PENDING, 2.0), (entry("A", 1, 11.0), LATE, 2.0)]
        assert opened.insert_messages(again) == [False, True]
        opened.commit_group([("A", 0), ("B", 0)], tracks(2), {"n": 1}, 10.0, {"groups": 1})
    with sqlite3.connect(path) as connection:
        (sql,) = connection.execute("SELECT sql FROM sqlite_master WHERE name = 'inbox'").fetchone()
    assert ("WITHOUT ROWID" in sql) == earlier
    with RuntimeStore(path) as reopened:
        assert reopened.status_counts() == {PROCESSED: 2, LATE: 1}
        assert reopened.counters()["duplicates"] == 1
        assert [stored.received_at for stored in reopened.messages(PROCESSED)] == [1.0, 1.0]
        assert reopened.insert_messages([(entry("B", 0), PENDING, 3.0)]) == [False]
