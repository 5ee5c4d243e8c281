"""Connected components of the small graphs the fusion tracker builds every window.

The tracker groups detections and tracks by compatibility a few times per window, on graphs
of tens to hundreds of nodes. SciPy's ``connected_components`` needs a sparse matrix, whose
construction and validation cost several times the search itself at that size; this
vectorised union of the edge lists gives the same labels without them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

_SMALL_GRAPH = 200  # nodes + edges up to which a search in Python beats numpy's rounds


def component_labels(
    node_count: int, first: NDArray[np.integer], second: NDArray[np.integer]
) -> NDArray[np.int64]:
    """Labels of the connected components of an undirected graph given by its edges.

    Args:
        node_count: nodes ``0 .. node_count - 1``.
        first: (E,) integer one end of each edge.
        second: (E,) integer the other end (self-loops and repeated edges are allowed).

    Returns:
        (node_count,) int64 labels ``0 .. K-1``, numbered in the order of each component's
        lowest node (the labels of ``scipy.sparse.csgraph.connected_components`` on the same
        graph, ``directed=False``).

    Example:
        >>> component_labels(5, np.array([3, 1]), np.array([4, 0])).tolist()
        [0, 0, 1, 2, 2]
    """
    first = np.asarray(first, dtype=np.int64)
    second = np.asarray(second, dtype=np.int64)
    if first.shape != second.shape or first.ndim != 1:
        raise ValueError(
            f"edge ends must be two 1-D arrays of one length, got {first.shape} and "
            f"{second.shape}"
        )
    if len(first) and (min(first.min(), second.min()) < 0
                       or max(first.max(), second.max()) >= node_count):
        raise ValueError(f"edge ends must lie in 0..{node_count - 1}")
    if node_count + len(first) <= _SMALL_GRAPH:
        return _small_component_labels(node_count, first.tolist(), second.tolist())
    # Every node points to a node of lower or equal index; a root points to itself. Each
    # round hooks the root of every edge's higher end under the lower root, then jumps
    # pointers until each node points at its root. The lowest node of a component is never
    # hooked, so it ends as the root of all of it.
    root = np.arange(node_count, dtype=np.int64)
    while True:
        root_first, root_second = root[first], root[second]
        crossing = root_first != root_second
        if not crossing.any():
            break
        low = np.minimum(root_first[crossing], root_second[crossing])
        high = np.maximum(root_first[crossing], root_second[crossing])
        np.minimum.at(root, high, low)
        while True:
            jumped = root[root]
            if np.array_equal(jumped, root):
                break
            root = jumped
    # Roots are the components' lowest nodes: numbering them in node order numbers the
    # components by their lowest node.
    number = np.cumsum(root == np.arange(node_count)) - 1
    return number[root].astype(np.int64, copy=False)


def _small_component_labels(node_count: int, first: list[int], second: list[int]
                            ) -> NDArray[np.int64]:
    """:func:`component_labels` of a small graph: the same labels, by a search in Python (a
    window's graph of a few detections and tracks costs microseconds, not the numpy calls of
    the vectorised rounds). Components are numbered as found, from the lowest node up."""
    neighbours: list[list[int]] = [[] for _ in range(node_count)]
    for one, other in zip(first, second, strict=True):
        neighbours[one].append(other)
        neighbours[other].append(one)
    label = [-1] * node_count
    count = 0
    for start in range(node_count):
        if label[start] >= 0:
            continue
        label[start] = count
        stack = [start]
        while stack:
            for other in neighbours[stack.pop()]:
                if label[other] < 0:
                    label[other] = count
                    stack.append(other)
        count += 1
    return np.array(label, np.int64)
