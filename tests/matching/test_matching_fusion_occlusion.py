"""Fusion tracker: people missed by every camera because nearer people hide them
(:mod:`cblrs.matching.fusion.occlusion`)."""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.occlusion import Hidden
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable
from cblrs.plane import PlaneSet, PlaneSpec

PLANES = PlaneSet([PlaneSpec(1, (-20.0, -20.0), 40.0, 40.0)])
# Two cameras 3 m high: west looks along +x, south along +y.
POSITIONS = {"west": (-15.0, 0.0, 3.0), "south": (0.0, -15.0, 3.0)}


def stage(**options) -> Hidden:
    config = FusionConfig(camera_positions=POSITIONS, **options)
    camera_xy = np.array([POSITIONS["west"][:2], POSITIONS["south"][:2]])
    context = FusionContext(config, ["west", "south"], camera_xy,
                            np.zeros(len(CLASS_NAMES) + 1), np.ones(len(CLASS_NAMES) + 1),
                            NoiseModel(0.2, 0.03))
    coverage = Coverage(PLANES, 2)
    whole = np.array([[x, y] for x in np.arange(-19.5, 20, 1.0) for y in np.arange(-19.5, 20, 1.0)])
    for camera in range(2):
        coverage.set_view(camera, whole)
    return Hidden(context, coverage)


def tracks_at(points) -> TrackTable:
    """Confirmed people (ids 1, 2, ...) standing at ``points``."""
    points = np.asarray(points, float).reshape(-1, 2)
    count = len(points)
    state = np.zeros((count, 4))
    state[:, :2] = points
    covariance = np.repeat(np.eye(4)[None] * 0.01, count, axis=0)
    return TrackTable(
        ids=np.arange(1, count + 1), class_id=np.zeros(count, np.int64), state=state,
        covariance=covariance, mode_state=state[:, None].copy(),
        mode_covariance=covariance[:, None].copy(), mode_probability=np.ones((count, 1)),
        evidence=np.full(count, 10), last_seen=np.zeros(count), seen_by=np.zeros((count, 2)),
        velocity_sigma=np.full(count, 0.1), heading=np.zeros((count, 2)),
        heading_time=np.zeros(count), heading_sigma=np.zeros(count), born=np.zeros(count),
    )


def detections(points, cameras) -> tuple[Observations, Measured]:
    points = np.asarray(points, float).reshape(-1, 2)
    camera = np.asarray(cameras, np.int64)
    count = len(points)
    observed = Observations(points, np.zeros((count, 3), np.int64), camera,
                            np.zeros((count, 4)), np.ones(count), np.zeros(count, np.int64))
    camera_xy = np.array([POSITIONS["west"][:2], POSITIONS["south"][:2]])[camera]
    offset = points - camera_xy
    distance = np.hypot(offset[:, 0], offset[:, 1])
    return observed, Measured(distance, distance, offset / distance[:, None],
                              np.full(count, 0.2))


def test_a_person_is_hidden_only_behind_a_nearer_detection_in_every_covering_view():
    hidden = stage()
    hidden.occluded_views, hidden.occluded_missed = 100.0, 90.0  # a detector that misses them
    # Track 1 at (1, 1): west sees a person at (0, 1) in front of it, south one at (1, 0).
    # Track 2 at (5, 5): west has someone in front ((4, 5)), south has nobody on its ray.
    # Track 3 at (-5, -5): its occluders stand behind it, not in front.
    tracks = tracks_at([[1.0, 1.0], [5.0, 5.0], [-5.0, -5.0]])
    observed, measured = detections(
        [[0.0, 1.0], [1.0, 0.0], [4.0, 5.0], [8.0, 5.0], [-5.0, -3.0], [-2.0, -5.0]],
        [0, 1, 0, 1, 0, 0])
    result = hidden.hidden(tracks, np.ones(3, dtype=bool), observed, measured)
    assert result.tolist() == [True, False, False]
    # Only the tracks asked about are tested.
    assert not hidden.hidden(tracks, np.array([False, True, True]), observed, measured).any()


def test_nobody_is_reported_hidden_while_the_cameras_detect_people_through_occlusion():
    hidden = stage()
    tracks = tracks_at([[1.0, 1.0]])
    observed, measured = detections([[0.0, 1.0], [1.0, 0.0]], [0, 1])
    assert hidden.miss_rate == 0.0
    assert not hidden.hidden(tracks, np.ones(1, dtype=bool), observed, measured).any()


def test_the_miss_rate_of_occluded_views_is_learnt_from_the_people_seen():
    hidden = stage()
    # Person 1 at (1, 1) stands right behind person 2 at (0, 1) as west sees them, and west
    # misses person 1; south sees both apart. Person 3 is in nobody's shadow.
    tracks = tracks_at([[1.0, 1.0], [0.0, 1.0], [6.0, -6.0]])
    observed, measured = detections([[0.0, 1.0], [1.0, 1.0], [0.0, 1.0], [6.0, -6.0]],
                                    [0, 1, 1, 1])
    assigned = np.array([1, 0, 1, 2])
    for _ in range(30):
        hidden.learn(tracks, np.ones(3, dtype=bool), observed, measured, assigned)
    # Each instant: one occluded view (person 1 in west), missed.
    assert hidden.occluded_views == 30.0 and hidden.occluded_missed == 30.0
    assert hidden.miss_rate > 0.5
    # Saved and restored with the tracker's state.
    other = stage()
    other.set_state(hidden.get_state())
    assert other.miss_rate == hidden.miss_rate


def test_off_when_report_hidden_s_is_zero():
    hidden = stage(report_hidden_s=0.0)
    tracks = tracks_at([[1.0, 1.0], [0.0, 1.0]])
    observed, measured = detections([[0.0, 1.0]], [0])
    hidden.learn(tracks, np.ones(2, dtype=bool), observed, measured, np.array([1]))
    assert hidden.occluded_views == 0.0


def test_missed_tracks_are_reported_hidden_only_for_report_hidden_s_behind_taken_detections():
    hidden = stage(report_hidden_s=1.0)
    hidden.occluded_views, hidden.occluded_missed = 100.0, 90.0
    tracks = tracks_at([[1.0, 1.0], [1.0, 1.0]])
    tracks.last_seen[:] = [9.5, 8.0]  # track 2 was missed for 2 s at time 10
    observed, measured = detections([[0.0, 1.0], [1.0, 0.0]], [0, 1])
    reported = np.zeros(2, dtype=bool)
    assert hidden.missed(tracks, reported, 10.0, observed, measured).tolist() == [True, False]
    # Already reported: nothing to add.
    assert not hidden.missed(tracks, np.ones(2, dtype=bool), 10.0, observed, measured).any()
    # Occluders no track took (a detector's false positives, say) hide nobody.
    untaken = np.zeros(2, dtype=bool)
    assert not hidden.missed(tracks, reported, 10.0, observed, measured, untaken).any()
