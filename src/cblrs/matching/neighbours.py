"""Pairs of points within a Chebyshev radius: a sorted sweep for few, a k-d tree for many.

The clock model looks, for each of a camera's recent detections, for the other cameras'
track positions near it in space and time. With a few dozen people there are a few
thousand pairs to compare, which a sort along one axis narrows to a few candidates; only
beyond that is the k-d tree used, and only then is ``scipy.spatial`` (a quarter of a second
to import) loaded. Both find the same pairs: the distance is the largest absolute coordinate
difference, the same floating-point operations either way.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

DENSE_PAIRS = 1 << 18
"""Up to this many query x point pairs are swept without the tree."""


def chebyshev_pairs(
    query: NDArray[np.float64], points: NDArray[np.float64], radius: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Every (query, point) pair at Chebyshev distance ``<= radius``.

    Args:
        query: (Q, D) float coordinates.
        points: (P, D) float coordinates.
        radius: the largest distance, in the coordinates' unit.

    Returns:
        ``(query_index, point_index)``: two (K,) int64 arrays, in no particular order.
    """
    query = np.asarray(query, np.float64)
    points = np.asarray(points, np.float64)
    if len(query) == 0 or len(points) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty
    if len(query) * len(points) > DENSE_PAIRS:
        # lazy: only many points need the tree (and SciPy's import)
        from scipy.spatial import cKDTree

        neighbours = cKDTree(points).query_ball_point(query, radius, p=np.inf,
                                                      return_sorted=False)
        lengths = np.fromiter((len(near) for near in neighbours), np.int64, len(neighbours))
        if not lengths.sum():
            empty = np.zeros(0, np.int64)
            return empty, empty
        near = np.concatenate([near for near in neighbours if near]).astype(np.int64)
        return np.repeat(np.arange(len(query), dtype=np.int64), lengths), near
    rows, columns = sweep_candidates(query, points, radius)
    for axis in range(query.shape[1]):
        keep = np.abs(query[rows, axis] - points[columns, axis]) <= radius
        rows, columns = rows[keep], columns[keep]
    return rows.astype(np.int64), columns.astype(np.int64)


def sweep_candidates(
    query: NDArray[np.float64], points: NDArray[np.float64], radius: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Every (query, point) pair whose first coordinates differ by at most ``radius``, and
    a few more: the points sorted by that coordinate, a window around each query, widened
    by far more than a rounding error so that it misses none. Exact tests on the pairs
    follow (any pair within ``radius`` in the Chebyshev or Euclidean metric is among them).

    Returns:
        ``(query_index, point_index)``: two (K,) int64 arrays.
    """
    order = np.argsort(points[:, 0], kind="stable")
    first = points[order, 0]
    slack = 1e-9 * (np.abs(query[:, 0]) + radius + 1.0)
    low = np.searchsorted(first, query[:, 0] - radius - slack, side="left")
    high = np.searchsorted(first, query[:, 0] + radius + slack, side="right")
    counts = np.maximum(high - low, 0)
    rows = np.repeat(np.arange(len(query), dtype=np.int64), counts)
    offset = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    return rows, order[np.repeat(low, counts) + offset].astype(np.int64)
