"""Which clicked points are gross mistakes: a consensus under the points' stated noise.

A wrong or swapped row is far beyond clicking error, but "far" depends on where the point is:
30 px off is a 5 cm ground error at the bottom of a frame and metres near the horizon. So the
test is the point's Mahalanobis distance under its own covariance (``click_px`` in the image
plus ``ground_m`` on the ground seen through the local pixels per metre, see
:mod:`cblrs.calibrate.refine`), not a distance in pixels: a point is an outlier when a
chi-square(2) value that large has a chance under 1 in 1000 (the threshold ``13.8``).

The consensus is MSAC (RANSAC scoring every point by its truncated distance) over the exact
homographies of 4 points: every 4 of up to 14 points, 1000 seeded random draws beyond. The
best consensus is refined and points are re-admitted or dropped until the set settles.
"""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.refine import PointNoise

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

OUTLIER_PROBABILITY = 1e-3
# chi-square(2) quantile: P(d^2 > t) = exp(-t / 2).
OUTLIER_DISTANCE = -2.0 * math.log(OUTLIER_PROBABILITY)
_SAMPLES = 1000


def homography_distances(
    homography: FloatArray, image_xy: FloatArray, world_xy: FloatArray, noise: PointNoise
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each point's squared Mahalanobis distance from a homography's prediction.

    Returns:
        ``(distance (N,), error_px (N,), depth (N,))``, the homography's sign chosen so that
        most points lie in front (depth > 0); a point behind has distance and error inf.
    """
    homogeneous = np.column_stack([world_xy, np.ones(len(world_xy))]) @ homography.T
    matrix = homography
    if np.median(homogeneous[:, 2]) < 0:
        homogeneous, matrix = -homogeneous, -homography
    depth = homogeneous[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        predicted = homogeneous[:, :2] / depth[:, None]
        # d(pixel)/d(world) of u = (H x)_12 / (H x)_3 is (H_12,12 - u H_3,12) / (H x)_3.
        jacobian = (matrix[None, :2, :2] - predicted[:, :, None] * matrix[None, 2:3, :2]) / depth[
            :, None, None
        ]
        covariance = noise.click_px**2 * np.eye(2) + noise.ground_m**2 * (
            jacobian @ jacobian.transpose(0, 2, 1)
        )
        residual = predicted - image_xy
        distance = np.einsum("ni,nij,nj->n", residual, np.linalg.inv(covariance), residual)
        error_px = np.hypot(*residual.T)
    bad = ~(depth > 0) | ~np.isfinite(distance)
    distance[bad] = np.inf
    error_px[bad] = np.inf
    return distance, error_px, depth


def consensus(
    image_xy: FloatArray,
    world_xy: FloatArray,
    noise: PointNoise,
    ransac_px: float | None = None,
) -> tuple[FloatArray, BoolArray]:
    """The homography of the largest consistent set of points, and that set.

    Args:
        image_xy: (N, 2) pixels, N >= 5.
        world_xy: (N, 2) metres.
        noise: the points' stated noise.
        ransac_px: when given, a point is an outlier beyond this many pixels from the
            homography instead (ignoring where on the ground it lies).

    Returns:
        ``(homography (3, 3), inliers (N,) bool)``; the homography is the least-squares one
        of the inliers (pixels), a start for the models' refinement.
    """
    count = len(image_xy)
    best: tuple[float, FloatArray] | None = None
    for sample in _samples(count):
        homography = _exact(world_xy[list(sample)], image_xy[list(sample)])
        if homography is None:
            continue
        cost = float(
            np.minimum(
                outlier_scores(homography, image_xy, world_xy, noise, ransac_px), OUTLIER_DISTANCE
            ).sum()
        )
        if best is None or cost < best[0]:
            best = (cost, homography)
    if best is None:
        # No 4 points in general position: the least-squares homography of all (the caller
        # refuses it if there is none).
        fallback, _ = cv2.findHomography(world_xy, image_xy, 0)
        matrix = np.full((3, 3), np.nan) if fallback is None else fallback
        return np.asarray(matrix, dtype=np.float64), np.ones(count, dtype=bool)
    homography = best[1]
    inliers = outlier_scores(homography, image_xy, world_xy, noise, ransac_px) <= OUTLIER_DISTANCE
    # The consensus of one minimal sample can leave out a good point (its 4 points are
    # noisy too): refit on the inliers and re-admit until the set settles.
    for _ in range(10):
        if inliers.sum() < 4:
            break
        refitted, _ = cv2.findHomography(world_xy[inliers], image_xy[inliers], 0)
        if refitted is None:
            break
        homography = np.asarray(refitted, dtype=np.float64)
        admitted = (
            outlier_scores(homography, image_xy, world_xy, noise, ransac_px) <= OUTLIER_DISTANCE
        )
        if np.array_equal(admitted, inliers) or admitted.sum() < 4:
            break
        inliers = admitted
    return homography, inliers


def outlier_scores(
    homography: FloatArray,
    image_xy: FloatArray,
    world_xy: FloatArray,
    noise: PointNoise,
    ransac_px: float | None = None,
) -> FloatArray:
    """(N,) squared distances compared with :data:`OUTLIER_DISTANCE` (see :func:`consensus`)."""
    distance, error_px, _ = homography_distances(homography, image_xy, world_xy, noise)
    if ransac_px is None:
        return distance
    # A pixel threshold, scaled so that it falls where the noise test's threshold does.
    return (error_px / ransac_px) ** 2 * OUTLIER_DISTANCE


def _samples(count: int) -> list[tuple[int, ...]]:
    if math.comb(count, 4) <= _SAMPLES:
        return list(itertools.combinations(range(count), 4))
    rng = np.random.default_rng(0)
    return [tuple(rng.choice(count, 4, replace=False).tolist()) for _ in range(_SAMPLES)]


def _exact(world: FloatArray, image: FloatArray) -> FloatArray | None:
    """The homography through 4 points, or None when 3 of them lie (nearly) on one line."""
    for points in (world, image):
        for triple in itertools.combinations(range(4), 3):
            a, b, c = points[list(triple)]
            area = abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
            extent = max(float(np.ptp(points, axis=0).max()), 1e-12)
            if area < 1e-3 * extent**2:
                return None
    homography = cv2.getPerspectiveTransform(world.astype(np.float32), image.astype(np.float32))
    if homography is None or not np.all(np.isfinite(homography)):
        return None
    return np.asarray(homography, dtype=np.float64)
