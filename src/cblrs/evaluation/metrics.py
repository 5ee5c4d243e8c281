"""HOTA, CLEAR (MOTA) and Identity (IDF1) scores of world tracks, with TrackEval.

The protocol is the AI City Challenge 2024 (track 1) one:

* all cameras of a scene collapse into one sequence: rows are keyed by (frame, id) only,
  ``camera_id`` is ignored;
* only the FIRST row per (frame, id) counts, for the ground truth and the predictions alike
  (later rows with the same key are dropped, whatever their position);
* the similarity of a ground-truth and a predicted position is
  ``max(0, 1 - distance / 2 m)`` (TrackEval's Euclidean similarity), used by HOTA over its
  19 thresholds alpha = 0.05 .. 0.95;
* MOTA (CLEAR) and IDF1 (Identity) match at TrackEval's default threshold 0.5 on that same
  similarity, i.e. within 1 m;
* the timesteps are the frames that hold ground truth (optionally restricted to a given set);
  prediction rows at other frames are ignored;
* optionally (``area``, on by default in ``cblrs eval`` and the CLI for WILDTRACK and
  MultiviewX, whose annotations cover only their annotated ground area): a prediction
  outside the area that lies farther than 1 m (the CLEAR / Identity match distance) from
  every ground-truth position of its frame is not scored. People standing outside the area
  are real but unannotated, like MOTChallenge's distractors; a prediction that could match
  a person at the border is still scored.

The dataset side (this module) builds TrackEval's per-sequence ``data`` dict and computes the
similarities; the metric classes (``trackeval.metrics.HOTA``, ``CLEAR``, ``Identity``) do the
scoring, so the figures are TrackEval's own.

Two TrackEval conventions worth knowing when reading the figures:

* LocA is the mean over the 19 alphas of the mean similarity of the matches at that alpha;
  TrackEval counts an alpha without any match as LocA 1. A constant 0.5 m error (similarity
  0.75) thus gives LocA = (15 x 0.75 + 4 x 1) / 19 = 80.3 %, not 75 % (``LocA(0)``, the
  value at alpha = 0.05, is in :meth:`Metrics.details`). With no match at any alpha (e.g. no
  predictions) LocA is undefined; it is reported as 0 here, where TrackEval says 100.
* HOTA is the mean over the alphas of sqrt(DetA_alpha x AssA_alpha), not sqrt(DetA x AssA).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cblrs.detections import Tracks
from cblrs.errors import DatasetError

logger = logging.getLogger(__name__)

ZERO_SIMILARITY_DISTANCE = 2.0
"""Metres at which the similarity of two positions reaches 0 (AI City 2024)."""

MATCH_THRESHOLD = 0.5
"""Similarity threshold of CLEAR and Identity: 0.5 is a distance of 1 m."""

SUMMARY_KEYS = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")


@dataclass(frozen=True)
class Metrics:
    """Tracking scores of one scene; the ratios are percentages (0..100).

    Attributes:
        HOTA: higher-order tracking accuracy, mean over alphas of sqrt(DetA x AssA).
        DetA: detection accuracy, TP / (TP + FN + FP), mean over alphas.
        AssA: association accuracy, mean over alphas.
        LocA: localisation accuracy, mean over alphas (see the module notes).
        MOTA: CLEAR MOTA at 1 m, (TP - FP - IDSW) / GT; can be negative.
        IDF1: identity F1 at 1 m.
        DetRe: detection recall (HOTA), mean over alphas.
        DetPr: detection precision (HOTA), mean over alphas.
        AssRe: association recall, mean over alphas.
        AssPr: association precision, mean over alphas.
        LocA0: LocA at the lowest alpha (0.05): mean similarity of nearly all matches.
        MOTP: CLEAR MOTP at 1 m: mean similarity of the CLEAR matches.
        IDP: identity precision at 1 m.
        IDR: identity recall at 1 m.
        IDSW: number of identity switches (CLEAR).
        true_positives: CLEAR matches at 1 m.
        false_positives: CLEAR false positives at 1 m.
        false_negatives: CLEAR misses at 1 m.
        num_timesteps: evaluated frames.
        num_gt_ids: ground-truth identities in the evaluated frames.
        num_predicted_ids: predicted identities in the evaluated frames.
        num_gt_dets: ground-truth rows evaluated (after de-duplication).
        num_predicted_dets: prediction rows evaluated (after de-duplication).
    """

    HOTA: float
    DetA: float
    AssA: float
    LocA: float
    MOTA: float
    IDF1: float
    DetRe: float = 0.0
    DetPr: float = 0.0
    AssRe: float = 0.0
    AssPr: float = 0.0
    LocA0: float = 0.0
    MOTP: float = 0.0
    IDP: float = 0.0
    IDR: float = 0.0
    IDSW: int = 0
    true_positives: int = 0
    false_positives: int = 0
    false_negatives: int = 0
    num_timesteps: int = 0
    num_gt_ids: int = 0
    num_predicted_ids: int = 0
    num_gt_dets: int = 0
    num_predicted_dets: int = 0

    def to_dict(self) -> dict[str, float]:
        """Exactly the six headline scores: HOTA, DetA, AssA, LocA, MOTA, IDF1 (percent)."""
        return {key: float(getattr(self, key)) for key in SUMMARY_KEYS}

    def details(self) -> dict[str, Any]:
        """Every field, headline scores first, then the extras."""
        return asdict(self)


def evaluate(
    ground_truth: Tracks,
    predictions: Tracks,
    frames: ArrayLike | None = None,
    area: tuple[float, float, float, float] | None = None,
) -> Metrics:
    """Score predicted world tracks against ground truth (AI City 2024 protocol).

    Args:
        ground_truth: ground-truth rows (``frame``, ``track_id``, ``world_xy`` in metres).
        predictions: predicted rows, same fields; ``camera_id``, ``xyxy`` and ``timestamp``
            are ignored.
        frames: (K,) int native frame numbers to evaluate; None evaluates every frame with
            ground truth. Frames without ground truth are never timesteps.
        area: the annotated ground area (x0, y0, width, length) metres, or None; see the
            module notes (predictions outside it and more than 1 m from every ground-truth
            position are not scored).

    Returns:
        The scores; see :class:`Metrics`.

    Raises:
        DatasetError: a ground-truth or predicted position is not finite.

    Example:
        >>> metrics = evaluate(scene.ground_truth, tracks)  # doctest: +SKIP
        >>> metrics.to_dict()  # doctest: +SKIP
        {'HOTA': 93.1, 'DetA': 91.0, 'AssA': 95.3, 'LocA': 90.2, 'MOTA': 97.0, 'IDF1': 97.9}
    """
    # lazy: TrackEval takes ~0.4 s to import; only scoring needs it
    from trackeval.metrics import CLEAR, HOTA, Identity

    data = build_trackeval_data(ground_truth, predictions, frames, area)
    hota = HOTA().eval_sequence(data)
    clear = CLEAR({"THRESHOLD": MATCH_THRESHOLD, "PRINT_CONFIG": False}).eval_sequence(data)
    identity = Identity({"THRESHOLD": MATCH_THRESHOLD, "PRINT_CONFIG": False}).eval_sequence(data)

    any_match = bool(np.any(np.asarray(hota["HOTA_TP"]) > 0))

    def percent_mean(field: str) -> float:
        return 100.0 * float(np.mean(hota[field]))

    return Metrics(
        HOTA=percent_mean("HOTA"),
        DetA=percent_mean("DetA"),
        AssA=percent_mean("AssA"),
        LocA=percent_mean("LocA") if any_match else 0.0,
        MOTA=100.0 * float(clear["MOTA"]),
        IDF1=100.0 * float(identity["IDF1"]),
        DetRe=percent_mean("DetRe"),
        DetPr=percent_mean("DetPr"),
        AssRe=percent_mean("AssRe"),
        AssPr=percent_mean("AssPr"),
        LocA0=100.0 * float(hota["LocA(0)"]) if any_match else 0.0,
        MOTP=100.0 * float(clear["MOTP"]),
        IDP=100.0 * float(identity["IDP"]),
        IDR=100.0 * float(identity["IDR"]),
        IDSW=int(clear["IDSW"]),
        true_positives=int(clear["CLR_TP"]),
        false_positives=int(clear["CLR_FP"]),
        false_negatives=int(clear["CLR_FN"]),
        num_timesteps=int(data["num_timesteps"]),
        num_gt_ids=int(data["num_gt_ids"]),
        num_predicted_ids=int(data["num_tracker_ids"]),
        num_gt_dets=int(data["num_gt_dets"]),
        num_predicted_dets=int(data["num_tracker_dets"]),
    )


def first_rows(tracks: Tracks) -> Tracks:
    """The first row of every (frame, track_id) pair, in the original row order."""
    if len(tracks) == 0:
        return tracks
    keys = np.stack([tracks.frame, tracks.track_id], axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    return tracks[np.sort(first)]


def outside_unmatched(
    ground_truth: Tracks, predictions: Tracks, area: tuple[float, float, float, float]
) -> NDArray[np.bool_]:
    """(P,) True for predictions outside ``area`` farther than 1 m from every ground-truth
    position of their frame (unannotated people; see the module notes).

    Args:
        ground_truth: ground-truth rows.
        predictions: predicted rows.
        area: (x0, y0, width, length) metres.
    """
    x0, y0, width, length = area
    xy = predictions.world_xy
    outside = (xy[:, 0] < x0) | (xy[:, 0] > x0 + width) | (xy[:, 1] < y0) | (xy[:, 1] > y0 + length)
    match_distance = ZERO_SIMILARITY_DISTANCE * (1.0 - MATCH_THRESHOLD)
    unmatched = outside.copy()
    for frame in np.unique(predictions.frame[outside]):
        rows = np.flatnonzero(outside & (predictions.frame == frame))
        truth_xy = ground_truth.world_xy[ground_truth.frame == frame]
        if len(truth_xy) == 0:
            continue
        distance = np.linalg.norm(xy[rows, None, :] - truth_xy[None, :, :], axis=2)
        unmatched[rows] = distance.min(axis=1) > match_distance
    return unmatched


def euclidean_similarity(
    ground_truth_xy: NDArray[np.float64], predicted_xy: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``max(0, 1 - distance / 2 m)`` between every ground-truth and predicted position.

    Args:
        ground_truth_xy: (G, 2) float64 metres.
        predicted_xy: (P, 2) float64 metres.

    Returns:
        (G, P) float64 similarities in 0..1.
    """
    distance = np.linalg.norm(ground_truth_xy[:, None, :] - predicted_xy[None, :, :], axis=2)
    return np.maximum(0.0, 1.0 - distance / ZERO_SIMILARITY_DISTANCE)


def build_trackeval_data(
    ground_truth: Tracks,
    predictions: Tracks,
    frames: ArrayLike | None = None,
    area: tuple[float, float, float, float] | None = None,
) -> dict[str, Any]:
    """TrackEval's per-sequence ``data`` dict under the AI City 2024 protocol.

    Returns:
        ``num_timesteps``, ``num_gt_ids``, ``num_tracker_ids``, ``num_gt_dets``,
        ``num_tracker_dets``, and per timestep ``gt_ids`` / ``tracker_ids`` ((G_t,) / (P_t,)
        int64, 0-based contiguous ids) and ``similarity_scores`` ((G_t, P_t) float64).
    """
    for name, tracks in (("ground truth", ground_truth), ("predictions", predictions)):
        if not np.all(np.isfinite(tracks.world_xy)):
            bad = int(np.flatnonzero(~np.isfinite(tracks.world_xy).all(axis=1))[0])
            raise DatasetError(
                f"{name} row {bad} (frame {int(tracks.frame[bad])}, id "
                f"{int(tracks.track_id[bad])}) has a non-finite world position."
            )
    timesteps = np.unique(ground_truth.frame)
    if frames is not None:
        timesteps = np.intersect1d(timesteps, np.asarray(frames, dtype=np.int64).ravel())
    truth = first_rows(ground_truth[np.isin(ground_truth.frame, timesteps)])
    predicted = first_rows(predictions[np.isin(predictions.frame, timesteps)])
    ignored = len(predictions) - len(predicted)
    if ignored:
        logger.debug("%d prediction rows are duplicates or at frames without ground truth", ignored)
    if area is not None and len(predicted):
        unannotated = outside_unmatched(truth, predicted, area)
        if unannotated.any():
            logger.debug(
                "%d prediction rows outside the annotated area match no ground truth; "
                "not scored", int(unannotated.sum()),
            )
            predicted = predicted[~unannotated]

    gt_labels, gt_ids = np.unique(truth.track_id, return_inverse=True)
    tracker_labels, tracker_ids = np.unique(predicted.track_id, return_inverse=True)
    gt_ids = gt_ids.reshape(-1).astype(np.int64)
    tracker_ids = tracker_ids.reshape(-1).astype(np.int64)

    gt_order = np.argsort(truth.frame, kind="stable")
    tracker_order = np.argsort(predicted.frame, kind="stable")
    gt_bounds = np.searchsorted(truth.frame[gt_order], timesteps, side="left")
    gt_ends = np.searchsorted(truth.frame[gt_order], timesteps, side="right")
    tracker_bounds = np.searchsorted(predicted.frame[tracker_order], timesteps, side="left")
    tracker_ends = np.searchsorted(predicted.frame[tracker_order], timesteps, side="right")

    gt_ids_per_step, tracker_ids_per_step, similarity_per_step = [], [], []
    for step in range(len(timesteps)):
        gt_rows = gt_order[gt_bounds[step] : gt_ends[step]]
        tracker_rows = tracker_order[tracker_bounds[step] : tracker_ends[step]]
        gt_ids_per_step.append(gt_ids[gt_rows])
        tracker_ids_per_step.append(tracker_ids[tracker_rows])
        similarity_per_step.append(
            euclidean_similarity(truth.world_xy[gt_rows], predicted.world_xy[tracker_rows])
        )
    return {
        "num_timesteps": len(timesteps),
        "num_gt_ids": len(gt_labels),
        "num_tracker_ids": len(tracker_labels),
        "num_gt_dets": len(truth),
        "num_tracker_dets": len(predicted),
        "gt_ids": gt_ids_per_step,
        "tracker_ids": tracker_ids_per_step,
        "similarity_scores": similarity_per_step,
    }
