"""Windows of nearby capture times: frame periods, window rules, completeness, chunking."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.detections import CameraMessage
from cblrs.matching.timing import (
    PeriodEstimator,
    WindowBuffer,
    form_window,
    waiting_for,
    window_complete,
)


def test_period_is_the_shortest_interval_and_ignores_dropped_frames():
    periods = PeriodEstimator(2)
    for timestamp in (0.0, 0.1, 0.2, 0.4, 0.5, 0.6):  # 0.3 was dropped
        periods.observe(0, timestamp)
    periods.observe(0, 0.55)  # not after the previous one: ignored
    assert periods.periods[0] == pytest.approx(0.1)  # the dropped frame does not count
    assert np.isnan(periods.periods[1])  # camera 1 never seen
    assert periods.last[0] == 0.6 and periods.last[1] == -np.inf
    assert periods.width(0.25, 0.3) == pytest.approx(0.03)
    assert PeriodEstimator(1).width(0.25, 0.3) == 0.25  # no period known yet


def test_a_run_of_dropped_frames_does_not_lengthen_the_period():
    """Five of eight intervals doubled by lost frames: a median would call the period 0.1 s
    and predict the next frame 70 ms after the last (it comes after 50 ms); the shortest
    interval does not."""
    periods = PeriodEstimator(1)
    timestamp = 0.0
    for interval in (0.05, 0.1, 0.1, 0.05, 0.1, 0.1, 0.1, 0.05):
        periods.observe(0, timestamp)
        timestamp += interval
    periods.observe(0, timestamp)
    assert periods.periods[0] == pytest.approx(0.05)


@pytest.mark.parametrize(
    ("times", "cameras", "width", "expected"),
    [
        ([0.0], [0], 0.1, (1, 0.1)),
        ([0.0, 0.01, 0.02], [0, 1, 2], 0.1, (3, 0.1)),  # three cameras within the width
        ([0.0, 0.05, 0.12], [0, 1, 2], 0.1, (2, 0.1)),  # the third is past the width
        ([0.0, 0.02, 0.04], [0, 0, 1], 0.1, (1, 0.02)),  # camera 0 again: closes the window
        ([0.0, 0.0, 0.0], [2, 0, 1], 0.01, (3, 0.01)),  # equal times
    ],
)
def test_form_window(times, cameras, width, expected):
    count, end = form_window(np.array(times), np.array(cameras), width)
    assert (count, end) == pytest.approx(expected)


def _waiting(members, times, end, passed, last, periods):
    return waiting_for(np.array(members, np.int64), np.array(times, float), end,
                       np.array(passed), np.array(last, float), np.array(periods, float))


@pytest.mark.parametrize(
    ("case", "members", "times", "passed", "last", "periods", "waiting"),
    [
        # Two cameras at one instant, periods unknown: both in, nothing can come between.
        ("both in, same time", [0, 1], [1.0, 1.0], [False, False], [1.0, 1.0],
         [np.nan, np.nan], [False, False]),
        # Camera 1 is in the window before camera 0's latest member: with no period known,
        # it might still send a message between them.
        ("earlier member, no period", [1, 0], [1.0, 1.02], [False, False], [1.02, 1.0],
         [np.nan, np.nan], [False, True]),
        ("earlier member, period", [1, 0], [1.0, 1.02], [False, False], [1.02, 1.0],
         [0.1, 0.1], [False, False]),
        # Camera 1 absent: waited for until it has moved past the window ...
        ("absent", [0], [1.0], [False, False], [1.0, 0.9], [np.nan, np.nan], [False, True]),
        ("absent, passed", [0], [1.0], [False, True], [1.0, 0.9], [np.nan, np.nan],
         [False, False]),
        # ... or its next frame is due after the end (a 2 fps camera among 10 fps ones) ...
        ("absent, not due", [0], [1.0], [False, False], [1.0, 0.8], [0.1, 0.5],
         [False, False]),
        # ... but not when it is due inside the window (it may have dropped that frame).
        ("absent, due", [0], [1.0], [False, False], [1.0, 0.9], [0.1, 0.1], [False, True]),
    ],
)
def test_waiting_for(case, members, times, passed, last, periods, waiting):
    assert _waiting(members, times, 1.03, passed, last, periods).tolist() == waiting
    assert window_complete(np.array(members), np.array(times), 1.03, np.array(passed),
                           np.array(last, float), np.array(periods, float)) == (not any(waiting))


def _message(camera: str, sequence: int, timestamp: float) -> CameraMessage:
    return CameraMessage(camera, sequence, timestamp, sequence, np.array([[0.0, 0, 10, 10]]),
                         np.array([0.9]), np.array([0]), np.array([[100 + sequence, 200, 1]]))


def _stream(seed: int) -> list[tuple[int, CameraMessage]]:
    """Three cameras at 10, 15 and 10 fps with clock offsets, jitter and dropped frames."""
    rng = np.random.default_rng(seed)
    messages = []
    for camera, (fps, offset) in enumerate([(10.0, 0.012), (15.0, -0.02), (10.0, 0.04)]):
        frames = np.arange(int(4 * fps))
        kept = frames[rng.random(len(frames)) > 0.1]
        times = kept / fps + offset + rng.normal(0, 0.003, len(kept))
        for sequence, timestamp in enumerate(np.maximum.accumulate(times).tolist()):
            messages.append((camera, _message(f"c{camera}", sequence, timestamp)))
    messages.sort(key=lambda item: (item[1].timestamp, item[0]))
    return messages


def _windows(messages, chunks: list[int], offsets: np.ndarray) -> list[list[tuple[str, int]]]:
    """Feed ``messages`` in chunks (each with its watermark) and collect the windows; at most
    the last two wait for the end of the stream."""
    buffer = WindowBuffer(3)
    windows = []
    start = 0
    for size in [*chunks, len(messages)]:
        part = messages[start:start + size]
        start += len(part)
        for camera, message in part:
            buffer.add(camera, message)
        if part:
            buffer.advance(part[-1][1].timestamp)
        while (window := buffer.next_window(offsets)) is not None:
            windows.append([(m.camera_id, m.sequence) for m in window.messages])
        if start >= len(messages):
            break
    released = len(windows)
    while (window := buffer.next_window(offsets, final=True)) is not None:
        windows.append([(m.camera_id, m.sequence) for m in window.messages])
    assert len(windows) - released <= 2
    return windows


@pytest.mark.parametrize("seed", range(6))
def test_windows_do_not_depend_on_how_messages_arrive(seed):
    """One message at a time, or in random batches (as a service receives them): the
    windows, and so the tracks, are the same."""
    messages = _stream(seed)
    offsets = np.array([0.012, -0.02, 0.04])  # what the clock model would have found
    one_by_one = _windows(messages, [1] * len(messages), offsets)
    rng = np.random.default_rng(seed)
    batches = _windows(messages, rng.integers(1, 12, len(messages)).tolist(), offsets)
    assert batches == one_by_one
    assert sum(len(window) for window in one_by_one) == len(messages)
    for window in one_by_one:  # one message per camera
        assert len({camera for camera, _ in window}) == len(window)


def test_corrected_windows_group_each_capture_instant():
    """With the offsets corrected, the windows are the capture instants: the 10 fps
    cameras' frames together, the 15 fps camera's on their own except every 0.2 s."""
    messages = _stream(0)
    windows = _windows(messages, [1] * len(messages), np.array([0.012, -0.02, 0.04]))
    times = {(m.camera_id, m.sequence): m.timestamp for _, m in messages}
    corrected = {"c0": 0.012, "c1": -0.02, "c2": 0.04}
    for window in windows[5:]:  # once the periods are known
        instants = [times[key] - corrected[key[0]] for key in window]
        assert max(instants) - min(instants) < 0.02


def test_buffer_state_round_trip():
    messages = _stream(1)
    buffer = WindowBuffer(3)
    for camera, message in messages[:20]:
        buffer.add(camera, message)
        buffer.advance(message.timestamp)
        buffer.next_window(np.zeros(3))
    copy = WindowBuffer(3)
    copy.set_state(json.loads(json.dumps(buffer.get_state())))
    assert len(copy) == len(buffer) > 0
    for camera, message in messages[20:]:
        for one in (buffer, copy):
            one.add(camera, message)
            one.advance(message.timestamp)
        first, second = buffer.next_window(np.zeros(3)), copy.next_window(np.zeros(3))
        assert (first is None) == (second is None)
        if first is not None and second is not None:
            assert [m.sequence for m in first.messages] == [m.sequence for m in second.messages]
            np.testing.assert_array_equal(first.times, second.times)
