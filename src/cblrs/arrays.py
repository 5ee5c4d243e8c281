"""Small array helpers for the hot paths of tracking (a window's few values at a time)."""

from __future__ import annotations

import numpy as np


def unique_integers(values: np.ndarray | list[int]) -> np.ndarray:
    """The sorted distinct values of integer (or bool) ``values``, as ``np.unique(values)``.

    ``np.unique``'s plain call consults ``numpy.ma`` (imported at its first use: some
    15 ms of a ``cblrs track`` process) and hashes; a sort and one comparison cost less on
    the few values of a window and give the same array (same values, order and dtype).
    Other dtypes (floats, where NaNs are merged) go to ``np.unique``.

    Args:
        values: any shape; flattened.

    Returns:
        (K,) the distinct values in increasing order.

    Example:
        >>> unique_integers(np.array([3, 1, 3, 2])).tolist()
        [1, 2, 3]
    """
    array = np.asarray(values)
    if array.dtype.kind not in "biu":
        return np.unique(array)
    array = np.sort(array, axis=None)
    if len(array) < 2:
        return array
    keep = np.empty(len(array), dtype=bool)
    keep[0] = True
    np.not_equal(array[1:], array[:-1], out=keep[1:])
    return array[keep]


def median_of_few(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a few float values (one per camera), without its
    overhead (a tenth of a millisecond, and ``numpy.ma`` imported at its first call): the
    middle value, or the two middle ones added and halved, as np.median's mean of them
    computes it.

    Args:
        values: (N,) float64.

    Example:
        >>> median_of_few(np.array([3.0, 1.0, 2.0, 10.0]))
        2.5
    """
    ordered = np.sort(values)
    if len(ordered) == 0 or np.isnan(ordered[-1]):  # NaN sorts last
        return float(np.median(values))
    middle = len(ordered) // 2
    if len(ordered) % 2:
        return float(ordered[middle])
    return float((ordered[middle - 1] + ordered[middle]) / 2)
