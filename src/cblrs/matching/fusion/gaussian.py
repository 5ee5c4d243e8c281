"""Gaussian algebra on the ground plane, shared by the fusion tracker's stages.

Ray-shaped covariances, Mahalanobis distances, information-form fusion of several views of one
object, and the search for close pairs of points (a k-d tree, or a dense matrix when small).
All functions are pure and vectorised over N.
"""

from __future__ import annotations

import numpy as np

from cblrs.matching import kalman
from cblrs.matching.neighbours import sweep_candidates

_DENSE_PAIRS = 20_000  # below this many N x T pairs a dense distance matrix is faster
# Up to this many finite pairs the k-d tree's answer is computed without the tree (and
# without importing scipy.spatial, a quarter of a second): a crowded window of WILDTRACK
# compares some 150 located detections with each other.
_TREE_FREE_PAIRS = 1 << 16


def ray_covariance(
    direction: np.ndarray, along_variance: np.ndarray, lateral_variance: np.ndarray
) -> np.ndarray:
    """(N, 2, 2) covariances elongated along unit ``direction`` (N, 2).

    ``along_variance`` and ``lateral_variance`` are (N,) square metres along and across it.
    """
    outer = direction[:, :, None] * direction[:, None, :]
    return (lateral_variance[:, None, None] * np.eye(2)[None]
            + (along_variance - lateral_variance)[:, None, None] * outer)


def largest_sigma(covariance: np.ndarray) -> np.ndarray:
    """(N,) square root of the largest eigenvalue of (N, 2, 2) covariances, metres."""
    half_trace = 0.5 * (covariance[:, 0, 0] + covariance[:, 1, 1])
    spread = np.hypot(0.5 * (covariance[:, 0, 0] - covariance[:, 1, 1]), covariance[:, 0, 1])
    return np.sqrt(half_trace + spread)


def inverse_cholesky_2x2(covariance: np.ndarray) -> np.ndarray:
    """(K, 2, 2) ``L^-1`` of the Cholesky factors ``L L^T`` of (K, 2, 2) SPD matrices.

    ``L^-1 d`` whitens a difference ``d`` of covariance ``L L^T``. Closed form: numpy's
    batched LAPACK calls cost far more than the arithmetic for 2 x 2 matrices.
    """
    first = np.sqrt(covariance[:, 0, 0])
    lower = covariance[:, 1, 0] / first
    second = np.sqrt(covariance[:, 1, 1] - lower * lower)
    inverse = np.zeros_like(covariance)
    inverse[:, 0, 0] = 1.0 / first
    inverse[:, 1, 0] = -lower / (first * second)
    inverse[:, 1, 1] = 1.0 / second
    return inverse


def mahalanobis_squared(difference: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """(K,) ``d^T C^-1 d`` for (K, 2) differences and (K, 2, 2) covariances."""
    a, b, d = covariance[:, 0, 0], covariance[:, 0, 1], covariance[:, 1, 1]
    dx, dy = difference[:, 0], difference[:, 1]
    return (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)


def fuse(
    labels: np.ndarray, count: int, world_xy: np.ndarray, covariance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information-weighted fusion of detections per label.

    Args:
        labels: (N,) int64 in 0..count-1.
        count: number of labels K.
        world_xy: (N, 2) metres.
        covariance: (N, 2, 2) square metres.

    Returns:
        ``(position (K, 2), covariance (K, 2, 2), present (K,) bool)``; rows of absent labels
        are NaN.
    """
    information, _ = kalman.inverse_2x2(covariance)
    weighted = np.einsum("nij,nj->ni", information, world_xy)
    # The information matrices' and vectors' sums per label in one bincount: each of the six
    # sums adds its terms in detection order, as six bincounts would.
    terms = np.concatenate([information.reshape(-1, 4), weighted], axis=1)  # (N, 6)
    keys = (np.asarray(labels, np.int64)[:, None] * 6 + np.arange(6)).reshape(-1)
    sums = np.bincount(keys, terms.reshape(-1), 6 * count).reshape(count, 6)
    total = sums[:, :4].reshape(count, 2, 2)
    vector = sums[:, 4:]
    present = np.bincount(labels, minlength=count) > 0
    fused_covariance = np.full((count, 2, 2), np.nan)
    position = np.full((count, 2), np.nan)
    if present.any():
        fused_covariance[present], _ = kalman.inverse_2x2(total[present])
        position[present] = np.einsum(
            "nij,nj->ni", fused_covariance[present], vector[present]
        )
    return position, fused_covariance, present


def close_pairs(
    points_xy: np.ndarray, targets_xy: np.ndarray, radius_m: np.ndarray, strict: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` with ``|points[i] - targets[j]| <= radius[i]``.

    Args:
        points_xy: (N, 2) metres.
        targets_xy: (T, 2) metres.
        radius_m: (N,) metres per point.
        strict: use ``<`` instead of ``<=``.

    Returns:
        ``(rows, columns)``, two (K,) int64 arrays in row-major order.
    """
    if len(points_xy) == 0 or len(targets_xy) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty
    if len(points_xy) * len(targets_xy) <= _DENSE_PAIRS:
        dx = points_xy[:, 0, None] - targets_xy[None, :, 0]
        dy = points_xy[:, 1, None] - targets_xy[None, :, 1]
        squared = dx * dx + dy * dy
        limit = (radius_m * radius_m)[:, None]
        rows, columns = np.nonzero(squared < limit if strict else squared <= limit)
        return rows.astype(np.int64), columns.astype(np.int64)
    # Many tracks: a k-d tree finds the few neighbours without touching all N x T pairs.
    finite_points = np.isfinite(points_xy).all(axis=1)
    finite_targets = np.isfinite(targets_xy).all(axis=1)
    point_index = np.flatnonzero(finite_points)
    target_index = np.flatnonzero(finite_targets)
    largest = float(np.max(radius_m))
    if len(point_index) * len(target_index) <= _TREE_FREE_PAIRS:
        pairs = _tree_pairs(points_xy[point_index], targets_xy[target_index], largest)
    else:
        # lazy: scipy.spatial takes a quarter of a second to import
        from scipy.spatial import cKDTree

        pairs = cKDTree(points_xy[point_index]).sparse_distance_matrix(
            cKDTree(targets_xy[target_index]), largest, output_type="ndarray"
        )
    rows = point_index[pairs["i"]]
    columns = target_index[pairs["j"]]
    distance = pairs["v"]
    keep = distance < radius_m[rows] if strict else distance <= radius_m[rows]
    rows, columns = rows[keep], columns[keep]
    order = np.lexsort((columns, rows))
    return rows[order].astype(np.int64), columns[order].astype(np.int64)


def _tree_pairs(points_xy: np.ndarray, targets_xy: np.ndarray, radius_m: float) -> dict:
    """What ``cKDTree(points).sparse_distance_matrix(cKDTree(targets), radius,
    output_type="ndarray")`` returns, up to the order of the pairs, without the tree: the
    candidates of a sweep along x (:func:`cblrs.matching.neighbours.sweep_candidates`), the
    squared distance summed axis by axis, kept when ``<= radius**2``, then its square root
    (the tree's own arithmetic, so the same pairs and the same distances).

    Returns:
        ``{"i": (K,) int64, "j": (K,) int64, "v": (K,) float64}``.
    """
    rows, columns = sweep_candidates(points_xy, targets_xy, radius_m)
    dx = points_xy[rows, 0] - targets_xy[columns, 0]
    dy = points_xy[rows, 1] - targets_xy[columns, 1]
    squared = dx * dx + dy * dy
    keep = squared <= radius_m * radius_m
    return {"i": rows[keep], "j": columns[keep], "v": np.sqrt(squared[keep])}


def camera_rays(world_xy: np.ndarray, camera_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays from cameras to points on the ground.

    Args:
        world_xy: (N, 2) points, metres.
        camera_xy: (N, 2) the ground position of each point's camera (NaN: not placed).

    Returns:
        (N,) metres from each point's camera (0 where the camera is not placed) and (N, 2)
        unit vectors from the camera to the point ((1, 0) where unknown).
    """
    offset = world_xy - camera_xy
    distance = np.linalg.norm(offset, axis=1)
    known = np.isfinite(distance) & (distance > 0)
    direction = np.zeros_like(offset)
    direction[:, 0] = 1.0
    direction[known] = offset[known] / distance[known, None]
    return np.where(known, distance, 0.0), direction
