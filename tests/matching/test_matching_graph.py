"""component_labels gives the labels of SciPy's connected_components on the same graph."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.matching.graph import component_labels


def _scipy_labels(node_count: int, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    # lazy: every pytest-xdist worker collects this file; SciPy's sparse graphs cost it
    # about half a CPU-second to import there, for the one worker that runs these tests
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(node_count, node_count))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("seed", range(40))
def test_labels_equal_scipys_on_random_graphs(seed):
    generator = np.random.default_rng(seed)
    node_count = int(generator.integers(1, 300))
    edge_count = int(generator.integers(0, 2 * node_count))
    first = generator.integers(0, node_count, edge_count)
    second = generator.integers(0, node_count, edge_count)
    labels = component_labels(node_count, first, second)
    assert labels.dtype == np.int64 and labels.shape == (node_count,)
    np.testing.assert_array_equal(labels, _scipy_labels(node_count, first, second))


def test_a_long_chain_numbered_from_its_far_end():
    """A path whose edges come from its highest node down (many hooking rounds)."""
    node_count = 1000
    order = np.arange(node_count)[::-1]
    labels = component_labels(node_count + 2, order[:-1], order[1:])
    assert labels.tolist() == [0] * node_count + [1, 2]


@pytest.mark.parametrize(
    "node_count, first, second, expected",
    [
        (0, [], [], []),
        (3, [], [], [0, 1, 2]),
        (3, [1], [1], [0, 1, 2]),  # a self-loop joins nothing
        (4, [2, 2, 3], [3, 3, 0], [0, 1, 0, 0]),  # repeated edges
    ],
)
def test_degenerate_graphs(node_count, first, second, expected):
    labels = component_labels(node_count, np.array(first, int), np.array(second, int))
    assert labels.tolist() == expected


@pytest.mark.parametrize(
    "first, second, message",
    [
        ([0, 1], [1], "two 1-D arrays of one length"),
        ([0], [3], r"lie in 0\.\.2"),
        ([-1], [0], r"lie in 0\.\.2"),
    ],
)
def test_bad_edges_are_refused(first, second, message):
    with pytest.raises(ValueError, match=message):
        component_labels(3, np.array(first), np.array(second))


@pytest.mark.parametrize("seed", range(20))
def test_small_graphs_searched_in_python_label_as_the_vectorised_rounds(seed, monkeypatch):
    """Graphs of up to _SMALL_GRAPH nodes and edges take a search in Python; larger ones the
    vectorised rounds. Both give the same labels (cliques: a window's views of one person)."""
    from cblrs.matching import graph

    generator = np.random.default_rng(seed)
    node_count = int(generator.integers(1, 40))
    clique = generator.permutation(node_count)[: int(generator.integers(1, 11))]
    pairs = [(int(a), int(b)) for a in clique for b in clique if a < b]
    extra = int(generator.integers(0, node_count))
    first = np.array([a for a, _ in pairs] + generator.integers(0, node_count, extra).tolist())
    second = np.array([b for _, b in pairs] + generator.integers(0, node_count, extra).tolist())
    assert node_count + len(first) <= graph._SMALL_GRAPH
    small = component_labels(node_count, first, second)
    monkeypatch.setattr(graph, "_SMALL_GRAPH", -1)
    rounds = component_labels(node_count, first, second)
    assert small.dtype == rounds.dtype == np.int64
    np.testing.assert_array_equal(small, rounds)
    np.testing.assert_array_equal(small, _scipy_labels(node_count, first, second))
