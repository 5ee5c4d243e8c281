"""Pairs of points within a Chebyshev radius: a dense comparison for few, a k-d tree for many.

The clock model looks, for each of a camera's recent detections, for the other cameras'
track positions near it in space and time. With a few dozen people there are a few
thousand pairs to compare, which numpy does at once; only beyond that is a k-d tree
worth building, and only then is ``scipy.spatial`` (a quarter of a second to import)
loaded. Both find the same pairs: the distance is the largest absolute coordinate
difference, the same floating-point operations either way.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

DENSE_PAIRS = 1 << 18
"""Up to this many query x point pairs are compared densely (a few MB at a time)."""


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
    rows_per_chunk = max(1, DENSE_PAIRS // len(points))
    found_query, found_point = [], []
    for start in range(0, len(query), rows_per_chunk):
        chunk = query[start:start + rows_per_chunk]
        distance = np.abs(chunk[:, None, :] - points[None, :, :]).max(axis=2)
        rows, columns = np.nonzero(distance <= radius)
        found_query.append(rows.astype(np.int64) + start)
        found_point.append(columns.astype(np.int64))
    return np.concatenate(found_query), np.concatenate(found_point)
