"""Fusion tracker: low-confidence detections, confirmed by a live track or another camera
(:mod:`cblrs.matching.fusion.low_confidence`)."""

from __future__ import annotations

import numpy as np
import pytest
from fusion_scenes import CAMERA_XY, CAMERAS, PLANES, run, sequence

from cblrs.detections import CameraMessage, Tracks
from cblrs.matching import FusionTracker, MatcherError
from cblrs.matching.base import Observations
from cblrs.matching.fusion.low_confidence import LowConfidence

WHOLE_PLAZA = np.array([[x, y] for x in np.arange(-9.5, 30, 1.0) for y in np.arange(-9.5, 30, 1.0)])
SURE, WEAK = 0.9, 0.3


def message(camera: str, frame: int, points, scores) -> CameraMessage:
    """One camera's frame at 2 fps: people at ``points`` (metres) with these scores."""
    points = np.asarray(points, float).reshape(-1, 2)
    colour, valid = PLANES[0].encode(points)
    assert valid.all()
    count = len(points)
    boxes = np.column_stack(
        [
            np.arange(count) * 50.0,
            np.zeros(count),
            np.arange(count) * 50.0 + 30.0,
            np.full(count, 80.0),
        ]
    )
    return CameraMessage(
        camera,
        frame,
        frame * 0.5,
        frame,
        boxes,
        np.asarray(scores, float).reshape(-1),
        np.zeros(count, np.int64),
        colour.astype(np.int64),
    )


def tracker(seen_by=(0, 1, 2), **options) -> FusionTracker:
    """Three cameras around the plaza; ``seen_by`` see all of it, the others none of it."""
    fusion = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY, **options)
    for camera in range(len(CAMERAS)):
        fusion.coverage.set_view(camera, WHOLE_PLAZA if camera in seen_by else np.zeros((0, 2)))
    return fusion


def track(fusion: FusionTracker, frames) -> Tracks:
    """Feed ``frames`` (per frame: {camera: (points, scores)}) and flush."""
    parts = []
    for frame, views in enumerate(frames):
        messages = [message(camera, frame, *view) for camera, view in views.items()]
        parts.append(fusion.update(frame * 0.5, messages))
    parts.append(fusion.flush())
    return Tracks.concatenate(parts)


def walker(frame: int) -> list[float]:
    return [1.0 + 0.6 * frame, 2.0]


def test_boxes_without_scores_track_exactly_as_without_the_stage():
    # Annotated boxes carry confidence 1: the stage must change nothing for them.
    instants = sequence(seed=3)
    with_stage = run(FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY), instants)
    without = run(
        FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY, high_confidence=0.0), instants
    )
    assert len(with_stage) > 0
    np.testing.assert_array_equal(with_stage.track_id, without.track_id)
    np.testing.assert_array_equal(with_stage.world_xy, without.world_xy)


@pytest.mark.parametrize("seen_by", [(0, 1, 2), (0,)])
def test_a_weak_box_alone_never_starts_a_track(seen_by):
    # One camera keeps reporting a weak box at one place: wherever the others look, it is
    # never a track. The same box scored high is one where that camera alone sees the
    # ground (no second camera could confirm it): reported from its second frame on.
    frames = [{"north": ([[6.0, 6.0]], [WEAK])} for _ in range(12)]
    assert len(track(tracker(seen_by), frames)) == 0
    sure = [{"north": ([[6.0, 6.0]], [SURE])} for _ in range(12)]
    assert len(track(tracker(seen_by), sure)) == (0 if len(seen_by) > 1 else 11)


def test_two_cameras_weak_boxes_of_one_place_start_nothing():
    frames = [{"north": ([[6.0, 6.0]], [WEAK]), "east": ([[6.1, 6.0]], [WEAK])} for _ in range(12)]
    assert len(track(tracker(), frames)) == 0


def test_three_cameras_weak_boxes_of_one_place_start_a_track():
    # Somebody every camera sees weakly (hidden in every view, or a multi-view detector
    # whose boxes share one score) is no one camera's mistake.
    place = [[6.0, 6.0]]
    frames = [{camera: (place, [WEAK]) for camera in CAMERAS} for _ in range(4)]
    tracks = track(tracker(), frames)
    assert tracks.frame.tolist() == [0, 1, 2, 3]
    assert set(tracks.track_id.tolist()) == {1}


def test_a_weak_box_confirms_another_cameras_sure_box_at_once():
    # North is sure of somebody, east sees him weakly: a track seen by two cameras from the
    # first frame (multi-view confirmation needs two where two cameras see the ground).
    person = [[6.0, 6.0]]
    alone = track(tracker(), [{"north": (person, [SURE])} for _ in range(4)])
    assert len(alone) == 0
    confirmed = track(
        tracker(), [{"north": (person, [SURE]), "east": (person, [WEAK])} for _ in range(4)]
    )
    assert confirmed.frame.tolist() == [0, 1, 2, 3]
    assert set(confirmed.track_id.tolist()) == {1}


def frames_of_a_walker_hidden_from(hidden: dict[str, float], start: int = 6, end: int = 10):
    """A walker all three cameras see surely; from ``start`` to ``end`` the cameras in
    ``hidden`` see him with that score (0: not at all)."""
    frames = []
    for frame in range(16):
        views = {}
        for camera in CAMERAS:
            score = hidden.get(camera, SURE) if start <= frame < end else SURE
            if score > 0:
                views[camera] = ([walker(frame)], [score])
        frames.append(views)
    return frames


def test_a_weak_view_extends_a_track_only_with_a_second_view():
    # North and east lose the walker for four frames; south sees him weakly.
    lone = track(tracker(), frames_of_a_walker_hidden_from({"north": 0, "east": 0, "south": WEAK}))
    # South alone, where the others look and see nothing, is weak evidence: the track
    # coasts through (not reported) and keeps its id.
    assert sorted(set(lone.frame.tolist())) == [*range(6), *range(10, 16)]
    assert set(lone.track_id.tolist()) == {1}
    # Two cameras' weak views of him, or one where only that camera sees the ground,
    # extend the track.
    two = track(
        tracker(), frames_of_a_walker_hidden_from({"north": 0, "east": WEAK, "south": WEAK})
    )
    alone_there = track(
        tracker(seen_by=(2,)),
        frames_of_a_walker_hidden_from({"north": 0, "east": 0, "south": WEAK}),
    )
    for tracks in (two, alone_there):
        assert sorted(set(tracks.frame.tolist())) == list(range(16))
        assert set(tracks.track_id.tolist()) == {1}
        assert np.abs(tracks.world_xy - [walker(f) for f in tracks.frame]).max() < 0.3
    # With a sure view by another camera, a weak one joins the track as well.
    sure_too = track(tracker(), frames_of_a_walker_hidden_from({"north": 0, "south": WEAK}))
    assert sorted(set(sure_too.frame.tolist())) == list(range(16))


def test_a_weak_second_box_of_one_camera_neither_displaces_nor_duplicates():
    # North reports the walker surely and a weak box 0.6 m off (a second box around him).
    frames = []
    for frame in range(10):
        views = {camera: ([walker(frame)], [SURE]) for camera in CAMERAS}
        views["north"] = ([np.add(walker(frame), [0.0, 0.6]), walker(frame)], [WEAK, SURE])
        frames.append(views)
    tracks = track(tracker(), frames)
    assert set(tracks.track_id.tolist()) == {1}
    assert np.abs(tracks.world_xy[:, 1] - 2.0).max() < 0.15


def observations(xy, camera, scores) -> Observations:
    count = len(camera)
    return Observations(
        np.asarray(xy, float),
        np.zeros((count, 3), np.int64),
        np.asarray(camera),
        np.zeros((count, 4)),
        np.asarray(scores, float),
        np.zeros(count, np.int64),
    )


def test_kept_rules_on_one_window():
    fusion = tracker()
    stage: LowConfidence = fusion.low_confidence
    tracks = fusion.tracks  # no tracks: every detection is a leftover
    observed = observations(
        [[0.0, 0.0], [0.1, 0.0], [5.0, 5.0], [5.1, 5.0], [9.0, 9.0], [12.0, 0.0]],
        [0, 1, 0, 1, 2, 2],
        [SURE, WEAK, WEAK, WEAK, SURE, WEAK],
    )
    covariance = np.tile(np.eye(2) * 0.04, (len(observed), 1, 1))
    kept = stage.kept(tracks, observed, covariance, np.full(len(observed), -1))
    # Sure ones always; a weak one next to another camera's sure one; not weak pairs, not
    # a weak one alone.
    assert kept.tolist() == [True, True, False, False, True, False]
    assert stage.is_high(observed).tolist() == [True, False, False, False, True, False]


@pytest.mark.parametrize("value", [-0.1, 1.5, "high", True])
def test_high_confidence_is_a_score(value):
    with pytest.raises(MatcherError, match="high_confidence"):
        FusionTracker(PLANES, CAMERAS, high_confidence=value)
