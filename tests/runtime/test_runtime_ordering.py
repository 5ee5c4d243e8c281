"""The matcher service's ordering, on its own: windows, release rules, drops, late messages."""

from __future__ import annotations

from typing import NamedTuple

import pytest

from cblrs.runtime.matcher.ordering import Orderer


class Entry(NamedTuple):
    camera_id: str
    timestamp: float


def released(orderer: Orderer, now: float = 0.0, **options) -> list[tuple[float, list[str]]]:
    return [(timestamp, [entry.camera_id for entry in entries])
            for timestamp, entries in orderer.release(now, **options)]


def feed(orderer: Orderer, camera: str, *timestamps: float, now: float = 0.0) -> None:
    for timestamp in timestamps:
        orderer.add(Entry(camera, timestamp), now)


def test_equal_timestamps_are_released_once_every_camera_is_in():
    orderer = Orderer(["A", "B"])
    feed(orderer, "A", 10.0, 11.0)
    assert released(orderer) == []
    feed(orderer, "B", 10.0)
    assert released(orderer) == [(10.0, ["A", "B"])]
    feed(orderer, "B", 11.0)
    assert released(orderer) == [(11.0, ["A", "B"])]
    assert len(orderer) == 0 and orderer.released == 11.0


def test_cameras_with_their_own_clocks_share_a_window():
    """Timestamps 5-40 ms apart (clock offsets) form one window, not one per camera."""
    orderer = Orderer(["A", "B", "C"])
    for frame in range(6):  # 2 fps
        feed(orderer, "A", frame * 0.5 + 0.005)
        feed(orderer, "B", frame * 0.5 - 0.03)
        feed(orderer, "C", frame * 0.5 + 0.04)
    windows = released(orderer) + released(orderer, force=True)
    assert [cameras for _, cameras in windows] == [["B", "A", "C"]] * 6
    assert [timestamp for timestamp, _ in windows] == pytest.approx(
        [frame * 0.5 + 0.04 for frame in range(6)])


def test_a_dropped_frame_is_passed_when_the_camera_moves_on():
    """B loses frame 2: that window is released as soon as B's frame 3 arrives, without
    waiting for any timeout."""
    orderer = Orderer(["A", "B"], timeout_s=3600.0)
    feed(orderer, "A", 0.0)
    feed(orderer, "B", 0.0)
    feed(orderer, "A", 0.1)
    feed(orderer, "B", 0.1)
    assert [cameras for _, cameras in released(orderer)] == [["A", "B"], ["A", "B"]]
    feed(orderer, "A", 0.2, 0.3)
    assert released(orderer) == []  # B may still send frame 2
    feed(orderer, "B", 0.3)
    assert released(orderer) == [(0.2, ["A"]), (0.3, ["A", "B"])]


def test_a_camera_not_due_is_not_waited_for():
    """Once the frame periods are known, a 2 fps camera among 10 fps ones is waited for
    only when its next frame may be due."""
    orderer = Orderer(["fast", "slow"], timeout_s=3600.0)
    for frame in range(20):
        feed(orderer, "fast", frame * 0.1)
        if frame % 5 == 0:
            feed(orderer, "slow", frame * 0.1)
    windows = released(orderer)
    # The slow camera's last frame is 1.5 s: the 1.6-1.8 s windows go without it, 1.9 s
    # waits (its frame due at 2.0 s could come up to 30 % of a period early).
    assert [timestamp for timestamp, _ in windows][-3:] == pytest.approx([1.6, 1.7, 1.8])
    assert [cameras for _, cameras in windows][-3:] == [["fast"]] * 3
    feed(orderer, "fast", 2.0)
    assert released(orderer) == []
    feed(orderer, "slow", 2.0)
    assert [cameras for _, cameras in released(orderer)] == [["fast"], ["fast", "slow"]]


def test_a_silent_camera_is_given_up_after_the_timeout_and_then_late():
    orderer = Orderer(["A", "B"], timeout_s=2.0)
    orderer.heard("B", 0.0)
    feed(orderer, "A", 10.0, now=0.0)
    assert released(orderer, now=1.0) == []
    assert released(orderer, now=2.5) == [(10.0, ["A"])]
    assert orderer.is_late(10.0) and orderer.is_late(9.0) and not orderer.is_late(10.01)


def test_a_camera_that_still_speaks_is_not_given_up():
    orderer = Orderer(["A", "B"], timeout_s=2.0)
    feed(orderer, "A", 10.0, now=0.0)
    orderer.heard("B", 2.4)  # e.g. it is replaying older frames more slowly
    assert released(orderer, now=2.5) == []


def test_offline_cameras_are_not_waited_for():
    orderer = Orderer(["A", "B"], timeout_s=3600.0)
    orderer.set_offline("B", True)
    feed(orderer, "A", 10.0)
    assert released(orderer) == [(10.0, ["A"])]
    assert orderer.offline == ["B"]


def test_limits_and_forced_release():
    orderer = Orderer(["A", "B"], timeout_s=3600.0, max_buffered_groups=3)
    feed(orderer, "A", 1.0, 2.0, 3.0)
    assert released(orderer) == [] and orderer.groups == 3
    feed(orderer, "A", 4.0)  # a fourth waiting time: the oldest goes regardless
    assert released(orderer) == [(1.0, ["A"])]
    assert released(orderer, force=True, limit=2) == [(2.0, ["A"]), (3.0, ["A"])]


def test_restore_resumes_the_release_point():
    """After a restart: the last released time and each camera's latest delivered time come
    from the store, pending messages are buffered again."""
    orderer = Orderer(["A", "B"])
    orderer.restore(5.0, {"A": 6.0, "B": 5.0, "unknown": 9.0})
    assert orderer.is_late(5.0) and not orderer.is_late(5.5)
    feed(orderer, "A", 6.0)  # pending in the store
    assert released(orderer) == []
    feed(orderer, "B", 6.0)
    assert released(orderer) == [(6.0, ["A", "B"])]


def test_bad_timeout():
    with pytest.raises(ValueError, match="finite number >= 0"):
        Orderer(["A"], timeout_s=float("nan"))
