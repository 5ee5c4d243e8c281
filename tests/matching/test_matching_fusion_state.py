"""Fusion tracker: snapshots (:mod:`cblrs.matching.fusion.state`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fusion_scenes import (
    CAMERA_XY,
    CAMERAS,
    PLANES,
    run,
    sequence,
)

from cblrs.detections import CameraMessage, Tracks
from cblrs.matching import FusionTracker, MatcherError


def test_state_round_trip_gives_the_same_output():
    instants = sequence(fps=5.0, seed=3, missing={(12, 0): True})
    uninterrupted = run(FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY), instants)
    first = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    head = run(first, instants[:17], flush=False)
    resumed = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    resumed.set_state(json.loads(json.dumps(first.get_state())))
    tail = run(resumed, instants[17:])
    joined = Tracks.concatenate([head, tail])
    np.testing.assert_array_equal(joined.track_id, uninterrupted.track_id)
    np.testing.assert_array_equal(joined.world_xy, uninterrupted.world_xy)
    np.testing.assert_array_equal(joined.frame, uninterrupted.frame)


def test_bad_state_and_unknown_camera():
    tracker = FusionTracker(PLANES, CAMERAS)
    with pytest.raises(MatcherError, match="not a saved fusion-tracker state"):
        tracker.set_state({})
    other = FusionTracker(PLANES, ["x"])
    with pytest.raises(MatcherError, match="saved state is for cameras"):
        tracker.set_state(other.get_state())
    with pytest.raises(MatcherError, match="unknown camera 'x'"):
        tracker.update(0.0, [CameraMessage.empty("x", 0, 0.0, 0)])

