"""Plausibility checks of a predictions file before it is scored.

A wrong file scores without complaint: an empty file scores 0, tracks of half the frames
score about half, frame *indices* (0, 1, 2, ...) where the ground truth has native frame
numbers (WILDTRACK: 0, 5, 10, ...) miss most frames, and positions in centimetres are 100
times too far away (HOTA 0). :func:`check_predictions` says which of these a file looks
like, one sentence each; ``cblrs eval`` prints them as warnings and still scores.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from cblrs.detections import Tracks

MIN_FRAME_COVERAGE = 0.9
"""Warn when predictions have rows in fewer than this share of the ground-truth frames."""
SCALE_LIMIT = 10.0
"""Warn when the predicted positions' spread differs from the ground truth's by more."""


def check_predictions(
    ground_truth: Tracks, predictions: Tracks, frames: ArrayLike | None = None
) -> list[str]:
    """Warnings (one sentence each) about a predictions file that looks wrong.

    Args:
        ground_truth: the ground-truth rows.
        predictions: the predicted rows.
        frames: native frame numbers being scored (None: every ground-truth frame).

    Returns:
        Empty when nothing looks wrong.
    """
    truth_frames = np.unique(ground_truth.frame if frames is None else np.asarray(frames))
    if frames is not None:
        ground_truth = ground_truth[np.isin(ground_truth.frame, truth_frames)]
    if len(predictions) == 0:
        return ["the predictions file has no rows: every ground-truth object counts as missed."]
    if len(truth_frames) == 0 or len(ground_truth) == 0:
        return []
    warnings = []
    predicted_frames = np.unique(predictions.frame)
    shared = np.intersect1d(predicted_frames, truth_frames)
    indices = np.arange(len(truth_frames))
    looks_like_indices = (
        len(shared) < 0.5 * len(truth_frames)
        and not np.array_equal(truth_frames, indices)
        and np.isin(predicted_frames, indices).mean() > 0.9
    )
    if looks_like_indices:
        step = np.diff(truth_frames)
        every = f" (every {int(step[0])}th)" if len(step) and np.all(step == step[0]) else ""
        warnings.append(
            f"the predicted frame numbers ({int(predicted_frames.min())}.."
            f"{int(predicted_frames.max())}) look like indices of the {len(truth_frames)} "
            f"ground-truth frames, not their native numbers ({int(truth_frames.min())}.."
            f"{int(truth_frames.max())}{every}); write native frame numbers."
        )
    elif len(shared) < MIN_FRAME_COVERAGE * len(truth_frames):
        warnings.append(
            f"the predictions have rows in {len(shared)} of the {len(truth_frames)} "
            f"ground-truth frames ({100 * len(shared) / len(truth_frames):.0f} %; predicted "
            f"frames {int(predicted_frames.min())}..{int(predicted_frames.max())}, ground "
            f"truth {int(truth_frames.min())}..{int(truth_frames.max())}): frames without "
            "predictions count as missed; use --frames to score a part."
        )
    scale = _spread(predictions.world_xy) / max(_spread(ground_truth.world_xy), 1e-9)
    if scale > SCALE_LIMIT or scale < 1.0 / SCALE_LIMIT:
        guess = ""
        if 30 <= scale <= 300:
            guess = " (centimetres instead of metres?)"
        elif 300 < scale <= 3000:
            guess = " (millimetres instead of metres?)"
        warnings.append(
            f"the predicted positions spread {scale:.3g} times as far as the ground truth's"
            f"{guess}; world positions must be metres in the ground truth's frame."
        )
    return warnings


def _spread(world_xy: np.ndarray) -> float:
    """A robust size of a point cloud: the larger 5-95 % range of x and y, metres."""
    points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 2:
        return 0.0
    low, high = np.percentile(points, [5, 95], axis=0)
    return float(np.max(high - low))
