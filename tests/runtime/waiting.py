"""Polling helpers shared by the runtime service tests."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_file import StoreNotReady

FIRST_POLL_S = 0.02
LAST_POLL_S = 0.1
"""The wait between two looks starts at 20 ms and grows to 100 ms: a condition met at once is
seen at once, and a wait of many seconds (a camera's replay, a broker's restart) does not cost
a core's tenth in looks (most predicates open a SQLite database or ask a broker: about 1 ms of
CPU each, 50 a second at a fixed 20 ms)."""


def wait_until(predicate: Callable[[], object], timeout: float, what: str) -> None:
    """Poll ``predicate`` (every 20 ms, then less often up to every 100 ms); fail the test
    with ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    pause = FIRST_POLL_S
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(pause)
        pause = min(LAST_POLL_S, pause * 1.25)


def wait_while_progressing(
    predicate: Callable[[], object], progress: Callable[[], object], stall_s: float, what: str
) -> None:
    """Poll ``predicate`` like :func:`wait_until`, for as long as ``progress()`` keeps changing;
    fail the test with ``what`` once it has not changed for ``stall_s`` seconds.

    For waits whose length is CPU work on a shared machine (tracking a backlog): a loaded
    machine makes them slower, never stuck, while a stall (a lost wake-up, a retry waiting
    for a timer) still fails within ``stall_s``. ``progress`` must be made of counts that
    only grow and are bounded (messages stored, messages tracked), so the wait ends.
    """
    seen = progress()
    changed = time.monotonic()
    pause = FIRST_POLL_S
    while not predicate():
        now = progress()
        if now != seen:
            seen, changed = now, time.monotonic()
        elif time.monotonic() - changed > stall_s:
            raise AssertionError(
                f"no progress for {stall_s:g} s (still at {seen}) waiting for {what}"
            )
        time.sleep(pause)
        pause = min(LAST_POLL_S, pause * 1.25)


def store_counter(database: Path, name: str) -> int:
    """A counter of a running matcher's database: 0 while the file is missing or its matcher
    is still creating it; any other problem with the file fails the test."""
    if not database.exists():
        return 0
    try:
        with RuntimeStore(database, read_only=True) as store:
            return store.counters().get(name, 0)
    except StoreNotReady:
        return 0
