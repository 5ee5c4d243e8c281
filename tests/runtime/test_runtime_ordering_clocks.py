"""Cameras whose clocks stamp a frame milliseconds apart: the ordering and the fusion tracker
release each frame as soon as its last camera's message is in, never after a timeout or the
next frame (issue 20 item 10); told the cameras' frame rate, from the first frame on.
Simulated time: what is measured is the rule, not the machine."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.bench.mqtt_load import PLANE, CameraClocks, camera_names
from cblrs.detections import CameraMessage, Tracks
from cblrs.matching import make_matcher
from cblrs.matching.timing import PeriodEstimator
from cblrs.plane import PlaneSet
from cblrs.runtime.matcher.ordering import Orderer

FPS = 10.0


def _messages(cameras: int, frames: int, clocks: CameraClocks, delay_s: float):
    """(arrival, message) of every camera's frames, two people walking, in arrival order."""
    names = camera_names(cameras)
    times = clocks.times(cameras, frames, FPS, 1000.0)
    generator = np.random.default_rng(5)
    events = []
    for frame in range(frames):
        for camera, name in enumerate(names):
            world = np.array([[5.0 + 0.1 * frame, 5.0], [8.0, 5.0 + 0.1 * frame]])
            colours, _ = PLANE.encode(world + generator.normal(0, 0.05, world.shape))
            message = CameraMessage(name, frame, float(times[frame, camera]), frame,
                                    np.tile([100.0, 100.0, 140.0, 220.0], (2, 1)),
                                    np.full(2, 0.9), np.zeros(2, np.int64),
                                    colours.astype(np.int64))
            events.append((float(times[frame, camera]) + delay_s, message))
    events.sort(key=lambda event: event[0])
    return names, events


@pytest.mark.parametrize("spread_ms, jitter_ms", [(0, 0), (10, 2), (25, 3)])
def test_each_frame_is_tracked_when_its_last_camera_arrives(spread_ms, jitter_ms):
    frames = 60
    names, events = _messages(12, frames, CameraClocks(spread_ms / 1000, jitter_ms / 1000, 1),
                              delay_s=0.003)
    last_arrival: dict[int, float] = {}
    for arrival, message in events:
        last_arrival[message.frame] = max(last_arrival.get(message.frame, 0.0), arrival)
    orderer = Orderer(names, timeout_s=2.0)
    matcher = make_matcher("fusion", PlaneSet([PLANE]), names)
    output_at: dict[int, float] = {}
    for arrival, message in events:
        orderer.add(message, arrival)
        for timestamp, group in orderer.release(arrival):
            tracks = matcher.update(timestamp, group)
            for frame in set(tracks.frame.tolist()):
                output_at.setdefault(frame, arrival)
    tracked = [frame for frame in range(10, frames - 1) if frame in output_at]
    assert len(tracked) == frames - 11  # every frame after the tracks' birth has rows
    late = [frame for frame in tracked if output_at[frame] > last_arrival[frame]]
    assert late == []


def _held_after_last_arrival(names, events, assumed_period_s):
    """Per frame: messages still held (ordering buffer + fusion tracker) once its last
    camera's message has been handled."""
    last_message = {}
    for index, (_, message) in enumerate(events):
        last_message[message.frame] = index
    orderer = Orderer(names, timeout_s=2.0, assumed_period_s=assumed_period_s)
    matcher = make_matcher("fusion", PlaneSet([PLANE]), names)
    tracks = []
    held = {}
    for index, (arrival, message) in enumerate(events):
        orderer.add(message, arrival)
        for timestamp, group in orderer.release(arrival):
            tracks.append(matcher.update(timestamp, group))
        if last_message[message.frame] == index:
            held[message.frame] = len(orderer) + matcher.waiting
    tracks.append(matcher.flush())
    return held, Tracks.concatenate(tracks)


@pytest.mark.parametrize("spread_ms, jitter_ms", [(0, 0), (10, 2), (25, 3)])
def test_told_the_frame_rate_no_frame_waits_from_the_first_on(spread_ms, jitter_ms):
    names, events = _messages(12, 12, CameraClocks(spread_ms / 1000, jitter_ms / 1000, 2),
                              delay_s=0.003)
    held, _ = _held_after_last_arrival(names, events, 1 / FPS)
    assert held == dict.fromkeys(range(12), 0)


def test_not_told_the_frame_rate_the_first_frames_wait_for_their_successors():
    names, events = _messages(12, 12, CameraClocks(0.010, 0.002, 2), delay_s=0.003)
    held, _ = _held_after_last_arrival(names, events, None)
    assert held[0] > 0  # frame 0 waits for the cameras' frame 1
    assert all(held[frame] == 0 for frame in range(6, 11))


def test_the_tracks_do_not_depend_on_when_windows_are_released():
    """Releasing the first frames at once, or after their successors, or everything at the
    end of the stream: the fusion tracker fuses the same windows, the same tracks."""
    names, events = _messages(12, 30, CameraClocks(0.010, 0.002, 3), delay_s=0.003)
    _, early = _held_after_last_arrival(names, events, 1 / FPS)
    _, waiting = _held_after_last_arrival(names, events, None)
    matcher = make_matcher("fusion", PlaneSet([PLANE]), names)
    messages = sorted((message for _, message in events), key=lambda one: one.timestamp)
    at_once = Tracks.concatenate([matcher.update(messages[-1].timestamp, messages),
                                  matcher.flush()])
    assert len(early) > 0
    for other in (waiting, at_once):
        assert np.array_equal(early.frame, other.frame)
        assert np.array_equal(early.track_id, other.track_id)
        assert np.array_equal(early.timestamp, other.timestamp)
        assert np.array_equal(early.world_xy, other.world_xy)


def test_a_camera_faster_than_told_is_predicted_from_its_second_frame():
    estimator = PeriodEstimator(2, assumed=0.1)
    assert np.isnan(estimator.periods).all()
    assert estimator.predicted.tolist() == [0.1, 0.1]
    estimator.observe(0, 1.0)
    estimator.observe(0, 1.04)
    assert estimator.predicted[0] == pytest.approx(0.04)
    assert estimator.predicted[1] == 0.1
    assert np.isnan(PeriodEstimator(2).predicted).all()
