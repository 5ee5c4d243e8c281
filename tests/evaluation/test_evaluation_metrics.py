"""evaluate() against hand-computed scores, with the real TrackEval underneath."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.detections import Tracks
from cblrs.errors import DatasetError
from cblrs.evaluation import Metrics, evaluate, first_rows
from cblrs.evaluation.metrics import build_trackeval_data

FRAMES = 10
HEADLINE = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")


def two_walkers(frames: int = FRAMES) -> Tracks:
    """Objects 0 and 1, 10 m apart (no cross-similarity), walking along x, every frame.

    Coordinates are exact binary fractions so that offsets give exact similarities.
    """
    frame = np.repeat(np.arange(frames), 2)
    track_id = np.tile([0, 1], frames)
    world_xy = np.stack([0.25 * frame, np.where(track_id == 0, 0.0, 10.0)], axis=1)
    return Tracks(frame, frame / 2.0, track_id, world_xy)


def with_changes(tracks: Tracks, **changes: np.ndarray) -> Tracks:
    return dataclasses.replace(tracks, **changes)


def test_perfect_tracks_score_100() -> None:
    truth = two_walkers()
    # Predicted ids are arbitrary labels: relabel them.
    predictions = with_changes(truth, track_id=truth.track_id * 7 + 100)
    metrics = evaluate(truth, predictions)
    assert metrics.to_dict() == {key: 100.0 for key in HEADLINE}
    assert (metrics.IDSW, metrics.num_gt_ids, metrics.num_predicted_ids) == (0, 2, 2)
    assert (metrics.num_timesteps, metrics.num_gt_dets, metrics.num_predicted_dets) == (10, 20, 20)


def test_to_dict_has_exactly_the_six_keys() -> None:
    metrics = evaluate(two_walkers(), two_walkers())
    assert list(metrics.to_dict()) == list(HEADLINE)
    assert set(metrics.details()) > set(HEADLINE)
    assert isinstance(metrics, Metrics)
    with pytest.raises(dataclasses.FrozenInstanceError):
        metrics.HOTA = 0.0  # type: ignore[misc]


def test_one_id_switch_halfway() -> None:
    """Object 0 is predicted as id 1 in frames 0-4 and id 3 in frames 5-9; object 1 is id 2.

    Every prediction sits on its object (similarity 1), so every alpha scores the same:
    TP = 20, FN = FP = 0 -> DetA = 1. Per (gt, predicted) pair, A = TPA / (TPA + FNA + FPA):
      (0, 1): TPA 5, gt 0 has 10 rows, id 1 has 5 -> A = 5 / (10 + 5 - 5) = 0.5
      (0, 3): likewise A = 0.5
      (1, 2): TPA 10 -> A = 10 / (10 + 10 - 10) = 1
    AssA = sum over TPs of A / TP = (5 x 0.5 + 5 x 0.5 + 10 x 1) / 20 = 0.75,
    AssRe = (5 x 5/10 + 5 x 5/10 + 10 x 1) / 20 = 0.75, AssPr = 1 (each id stays on one object),
    HOTA = sqrt(1 x 0.75). CLEAR: one switch -> MOTA = (20 - 0 - 1) / 20 = 0.95.
    Identity: best one-to-one is 0<->1 (5 IDTP), 1<->2 (10) -> IDTP 15, IDFN 5, IDFP 5 (id 3)
    -> IDF1 = 15 / (15 + 2.5 + 2.5) = 0.75.
    """
    truth = two_walkers()
    predicted_id = np.where(truth.track_id == 1, 2, np.where(truth.frame < 5, 1, 3))
    metrics = evaluate(truth, with_changes(truth, track_id=predicted_id))
    assert metrics.DetA == pytest.approx(100.0)
    assert metrics.AssA == pytest.approx(75.0)
    assert metrics.AssRe == pytest.approx(75.0)
    assert metrics.AssPr == pytest.approx(100.0)
    assert metrics.HOTA == pytest.approx(100.0 * np.sqrt(0.75))
    assert metrics.LocA == pytest.approx(100.0)
    assert metrics.IDSW == 1
    assert metrics.MOTA == pytest.approx(95.0)
    assert metrics.IDF1 == pytest.approx(75.0)
    assert metrics.num_predicted_ids == 3


def test_constant_half_metre_offset() -> None:
    """Every prediction 0.5 m off: similarity 1 - 0.5 / 2 = 0.75 for every match.

    HOTA's alphas are 0.05, 0.10, ..., 0.95 (19 values); the 15 alphas <= 0.75 match
    everything (LocA_alpha = 0.75, DetA_alpha = AssA_alpha = 1), the 4 above match nothing
    (DetA_alpha = AssA_alpha = 0, and TrackEval counts LocA_alpha as 1). Hence
    DetA = AssA = HOTA = 15 / 19, LocA = (15 x 0.75 + 4 x 1) / 19, LocA(0) = 0.75, and
    MOTA = IDF1 = 100 (0.5 m is inside the 1 m threshold).
    """
    truth = two_walkers()
    metrics = evaluate(truth, with_changes(truth, world_xy=truth.world_xy + np.array([0.5, 0.0])))
    assert metrics.LocA0 == pytest.approx(75.0)
    assert metrics.MOTP == pytest.approx(75.0)
    assert metrics.LocA == pytest.approx(100.0 * (15 * 0.75 + 4 * 1.0) / 19)
    for key in ("HOTA", "DetA", "AssA"):
        assert getattr(metrics, key) == pytest.approx(100.0 * 15 / 19), key
    assert metrics.MOTA == pytest.approx(100.0)
    assert metrics.IDF1 == pytest.approx(100.0)


@pytest.mark.parametrize(
    ("offset", "mota", "idf1"),
    [
        (0.99, 100.0, 100.0),
        # Beyond 1 m nothing matches: MOTA = (0 - 20 FP - 0) / 20 GT = -1.
        (1.01, -100.0, 0.0),
    ],
)
def test_one_metre_match_threshold(offset: float, mota: float, idf1: float) -> None:
    truth = two_walkers()
    shifted = with_changes(truth, world_xy=truth.world_xy + np.array([offset, 0.0]))
    metrics = evaluate(truth, shifted)
    assert metrics.MOTA == pytest.approx(mota)
    assert metrics.IDF1 == pytest.approx(idf1)


def test_only_the_first_row_per_frame_and_id_counts() -> None:
    truth = two_walkers()
    # A second camera reports every track again, 5 m off: these later rows must be ignored.
    far = with_changes(truth, world_xy=truth.world_xy + np.array([5.0, 0.0]), camera_id=np.ones(20))
    perfect = with_changes(truth, camera_id=np.zeros(20, np.int64))
    assert evaluate(truth, Tracks.concatenate([perfect, far])).to_dict()["HOTA"] == 100.0
    # The other way round the far rows come first and are the ones that count.
    assert evaluate(truth, Tracks.concatenate([far, perfect])).HOTA == 0.0
    # The same rule holds for the ground truth.
    far_truth = with_changes(truth, world_xy=truth.world_xy + np.array([5.0, 0.0]))
    assert evaluate(Tracks.concatenate([truth, far_truth]), truth).HOTA == 100.0
    assert evaluate(Tracks.concatenate([far_truth, truth]), truth).HOTA == 0.0


def test_first_rows_keeps_order() -> None:
    tracks = Tracks(
        frame=[3, 1, 3, 1],
        timestamp=[0, 0, 0, 0],
        track_id=[5, 5, 5, 6],
        world_xy=[[0, 0], [1, 1], [2, 2], [3, 3]],
    )
    np.testing.assert_array_equal(first_rows(tracks).world_xy, [[0, 0], [1, 1], [3, 3]])
    assert len(first_rows(Tracks.empty())) == 0


def test_empty_predictions_score_zero() -> None:
    metrics = evaluate(two_walkers(), Tracks.empty())
    assert metrics.to_dict() == {key: 0.0 for key in HEADLINE}
    assert metrics.false_negatives == 20
    empty = evaluate(Tracks.empty(), Tracks.empty())
    assert empty.to_dict() == {key: 0.0 for key in HEADLINE}
    assert empty.num_timesteps == 0


def test_predictions_at_frames_without_ground_truth_are_ignored() -> None:
    truth = two_walkers()
    extra = Tracks(
        frame=[100, 100, 7],
        timestamp=[50.0, 50.0, 3.5],
        track_id=[0, 9, 9],
        world_xy=[[0.0, 0.0], [3.0, 3.0], [50.0, 50.0]],
    )
    baseline = evaluate(truth, truth).details()
    # Frame 100 has no ground truth; the row at frame 7 is a real false positive.
    with_extra = evaluate(truth, Tracks.concatenate([truth, extra])).details()
    assert with_extra["num_predicted_dets"] == baseline["num_predicted_dets"] + 1
    assert with_extra["false_positives"] == 1
    without_frame_7 = evaluate(truth, Tracks.concatenate([truth, extra[:2]])).details()
    assert without_frame_7 == baseline


def test_frames_restrict_the_timesteps() -> None:
    truth = two_walkers()
    predicted_id = np.where(truth.track_id == 1, 2, np.where(truth.frame < 5, 1, 3))
    predictions = with_changes(truth, track_id=predicted_id)
    before_switch = evaluate(truth, predictions, frames=np.arange(0, 5))
    assert before_switch.to_dict() == {key: 100.0 for key in HEADLINE}
    assert before_switch.num_timesteps == 5
    # Frames outside the ground truth are not timesteps.
    assert evaluate(truth, predictions, frames=[3, 40]).num_timesteps == 1
    assert evaluate(truth, predictions, frames=[]).num_timesteps == 0


def test_trackeval_data_is_contiguous_and_per_timestep() -> None:
    truth = two_walkers(3)
    predictions = with_changes(truth, track_id=truth.track_id + 1000)[:5]
    data = build_trackeval_data(truth, predictions)
    assert data["num_timesteps"] == 3
    assert (data["num_gt_ids"], data["num_tracker_ids"]) == (2, 2)
    assert [ids.tolist() for ids in data["tracker_ids"]] == [[0, 1], [0, 1], [0]]
    assert [scores.shape for scores in data["similarity_scores"]] == [(2, 2), (2, 2), (2, 1)]
    np.testing.assert_allclose(data["similarity_scores"][0], np.eye(2))


@pytest.mark.parametrize("which", ["ground truth", "predictions"])
def test_non_finite_positions_are_rejected(which: str) -> None:
    truth = two_walkers()
    broken_xy = truth.world_xy.copy()
    broken_xy[3] = np.nan
    broken = with_changes(truth, world_xy=broken_xy)
    arguments = (broken, truth) if which == "ground truth" else (truth, broken)
    with pytest.raises(DatasetError, match=f"{which} row 3 \\(frame 1, id 1\\) has a non-finite"):
        evaluate(*arguments)


@settings(max_examples=25, deadline=None)
@given(
    presence=st.lists(st.lists(st.booleans(), min_size=4, max_size=4), min_size=1, max_size=8),
    noise=st.floats(-1.0, 1.0),
    shuffle_seed=st.integers(0, 2**16),
)
def test_ground_truth_against_itself_is_perfect(
    presence: list[list[bool]], noise: float, shuffle_seed: int
) -> None:
    """Any set of well-separated objects (5 m apart), in any row order, scores 100 on itself."""
    mask = np.array(presence)
    frame, track_id = np.nonzero(mask)
    if len(frame) == 0:
        return
    world_xy = np.stack([5.0 * track_id + noise, np.full(len(frame), noise)], axis=1)
    truth = Tracks(frame, frame / 2.0, track_id, world_xy)
    order = np.random.default_rng(shuffle_seed).permutation(len(truth))
    predictions = with_changes(truth[order], track_id=truth.track_id[order] + 50)
    assert evaluate(truth, predictions).to_dict() == {key: 100.0 for key in HEADLINE}


def test_wildtrack_ground_truth_against_itself(wildtrack_root) -> None:
    from cblrs.datasets import load_scene

    truth = load_scene(wildtrack_root).ground_truth
    metrics = evaluate(truth, truth)
    assert metrics.to_dict() == {key: 100.0 for key in HEADLINE}
    assert metrics.num_timesteps == len(np.unique(truth.frame))
    # Drop every other frame of the predictions: half the detections are missed.
    kept = truth[np.isin(truth.frame, np.unique(truth.frame)[::2])]
    assert evaluate(truth, kept).DetRe == pytest.approx(100.0 * len(kept) / len(truth))
