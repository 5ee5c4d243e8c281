"""Fusion tracker: births, the clustering of unassigned detections across cameras
(:mod:`cblrs.matching.fusion.birth`)."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.matching.fusion import (
    cluster_detections,
)


@pytest.mark.parametrize(
    ("points", "cameras", "expected"),
    [
        ([], [], []),
        ([(0, 0)], [0], [0]),
        ([(0, 0), (0.3, 0)], [0, 1], [0, 0]),  # two cameras, close: one object
        ([(0, 0), (0.3, 0)], [0, 0], [0, 1]),  # one camera sees two objects
        ([(0, 0), (3, 0)], [0, 1], [0, 1]),  # too far apart
        # complete linkage: a chain 0 -- 0.8 -- 1.6 is not one object within 1 m
        ([(0, 0), (0.8, 0), (1.6, 0)], [0, 1, 2], [0, 0, 1]),
    ],
)
def test_cluster_detections(points, cameras, expected):
    labels = cluster_detections(np.asarray(points, float).reshape(-1, 2),
                                np.asarray(cameras, np.int64), 0.2, 3.5)
    assert labels.tolist() == expected


@pytest.mark.parametrize("seed", range(40))
def test_clusters_are_complete_linkage_with_one_view_per_camera(seed):
    """Random crowds (dense enough that the greedy merge runs): every cluster holds one
    detection per camera and only compatible pairs, and no two clusters could still merge."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(10, 120))
    world_xy = rng.uniform(0, rng.uniform(1.0, 5.0), size=(count, 2))
    camera = rng.integers(0, int(rng.integers(2, 20)), count)
    sigma = rng.uniform(0.05, 0.4, count)
    labels = cluster_detections(world_xy, camera, sigma, 3.0)
    distance = np.linalg.norm(world_xy[:, None] - world_xy[None], axis=2)
    compatible = distance <= 3.0 * np.sqrt(sigma[:, None] ** 2 + sigma[None] ** 2)
    clusters = [np.flatnonzero(labels == label) for label in np.unique(labels)]
    for members in clusters:
        assert len(set(camera[members].tolist())) == len(members)
        assert compatible[np.ix_(members, members)].all()
    for index, one in enumerate(clusters):
        for other in clusters[index + 1:]:
            mergeable = (not set(camera[one].tolist()) & set(camera[other].tolist())
                         and compatible[np.ix_(one, other)].all())
            assert not mergeable



def test_cluster_labels_of_a_few_detections_number_as_the_vectorised_path(monkeypatch):
    """Up to _FEW_DETECTIONS detections are renumbered in Python, more with numpy: the same
    labels (numbered by first member)."""
    from cblrs.matching.fusion import birth

    generator = np.random.default_rng(5)
    for _ in range(50):
        count = int(generator.integers(1, 60))
        world_xy = generator.uniform(0, 6, (count, 2))
        camera = generator.integers(0, 4, count)
        few = birth.cluster_detections(world_xy, camera, 0.3, 3.0)
        monkeypatch.setattr(birth, "_FEW_DETECTIONS", -1)
        many = birth.cluster_detections(world_xy, camera, 0.3, 3.0)
        monkeypatch.undo()
        assert few.dtype == many.dtype == np.int64
        np.testing.assert_array_equal(few, many)
