"""Cameras whose clocks stamp a frame milliseconds apart: the ordering and the fusion tracker
release each frame as soon as its last camera's message is in, never after a timeout or the
next frame (issue 20 item 10). Simulated time: what is measured is the rule, not the machine."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.bench.mqtt_load import PLANE, CameraClocks, camera_names
from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
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
