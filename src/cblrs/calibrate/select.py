"""Choosing a model by how well it predicts points it was not fitted to.

More parameters always fit the clicked points better; what matters is the ground the points
do not cover. Each candidate model is cross-validated (leave-one-out up to 10 points, 10
folds beyond): refitted without a point, it predicts that point, and the point's squared
Mahalanobis distance under its stated noise (:func:`cblrs.calibrate.refine.normalised_errors`)
scores the prediction. The chosen model is the simplest whose mean held-out score is within
one standard error of the best (Breiman's one-standard-error rule): a richer model must earn
its parameters on held-out points.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.refine import (
    FOCAL,
    HOMOGRAPHY,
    K1,
    POSE,
    PointNoise,
    Refined,
    normalised_errors,
    refine,
)
from cblrs.errors import CalibrationError

FloatArray = NDArray[np.float64]

# Simplest first: fewer parameters, then fewer assumptions about the lens (a homography
# assumes nothing about the lens but that it has none; k1 adds a parameter that
# extrapolates into the frame's corners).
ORDER = (POSE, FOCAL, HOMOGRAPHY, K1)
FOLDS = 10
TIE = 0.1


@dataclass(frozen=True, eq=False)
class HeldOut:
    """How a model predicts each point when fitted without it.

    Attributes:
        model: the model.
        distance: (N,) squared Mahalanobis distance of each held-out point (inf when the
            model fitted without it puts it behind the camera).
        error_px: (N,) pixel distance of each held-out point from its prediction.
        error_m: (N,) ground distance, metres, of each held-out point's clicked pixel
            located by the model fitted without it (NaN above its horizon).
    """

    model: str
    distance: FloatArray
    error_px: FloatArray
    error_m: FloatArray

    @property
    def score(self) -> float:
        """Mean squared normalised error of the held-out points (2 when they fit as stated)."""
        return float(np.mean(self.distance))

    @property
    def standard_error(self) -> float:
        if not np.all(np.isfinite(self.distance)):
            return math.inf
        return float(np.std(self.distance, ddof=1) / math.sqrt(len(self.distance)))


def cross_validate(
    refined: Refined, image_xy: FloatArray, world_xy: FloatArray, noise: PointNoise
) -> HeldOut | None:
    """Cross-validate a fitted model on its points; None when its folds are too small.

    A fold's refit starts from the full fit (a warm start: it only has to move as far as
    leaving the fold out moves it).
    """
    count = len(image_xy)
    folds = min(count, FOLDS)
    training = count - math.ceil(count / folds)
    parameterisation = refined.parameterisation
    if 2 * training < parameterisation.size:
        return None
    fold = np.arange(count) % folds
    distance = np.empty(count)
    error_px = np.empty(count)
    error_m = np.empty(count)
    for index in range(folds):
        held = fold == index
        trained = refine(parameterisation, refined.params, image_xy[~held], world_xy[~held], noise)
        distance[held] = normalised_errors(
            parameterisation, trained.params, image_xy[held], world_xy[held], noise
        )
        predicted, depth = parameterisation.project(trained.params, world_xy[held])
        error_px[held] = np.where(depth > 0, np.hypot(*(predicted - image_xy[held]).T), np.inf)
        try:
            located, valid = trained.camera("held-out").pixel_to_world(image_xy[held])
        except (CalibrationError, np.linalg.LinAlgError):  # a degenerate refit: no location
            located, valid = np.full((int(held.sum()), 2), np.nan), np.zeros(int(held.sum()), bool)
        error_m[held] = np.where(valid, np.hypot(*(located - world_xy[held]).T), np.nan)
    return HeldOut(parameterisation.model, distance, error_px, error_m)


def choose(held_out: Mapping[str, HeldOut]) -> str | None:
    """The simplest model within one standard error of the best held-out score (None when
    no model predicts every held-out point in front of the camera)."""
    finite = {model: result for model, result in held_out.items() if math.isfinite(result.score)}
    if not finite:
        return None
    best = min(finite.values(), key=lambda result: result.score)
    # Scores differing by less than a twentieth of the noise level (2) are ties, so that
    # points without noise (all scores ~0) also get the simplest model.
    limit = best.score + max(best.standard_error, TIE)
    for model in ORDER:
        if model in finite and finite[model].score <= limit:
            return model
    return best.model
