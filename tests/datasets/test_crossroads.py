"""The signalised crossroads: queues at red, gaps kept, mixed classes, OD truth by construction."""

from __future__ import annotations

from collections import Counter

import numpy as np

from cblrs.analytics.site import load_site_places
from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets.crossroads import (
    ARMS,
    GREEN_S,
    crossroads_od,
    crossroads_world,
    signal_green,
)
from cblrs.datasets.paths import SampledPath
from cblrs.datasets.synthetic import SyntheticWorld
from cblrs.experiments.counts import find_sites


def test_signal_gives_each_arm_green_in_turn_then_pedestrians():
    times = np.arange(0.0, 200.0, 0.5)
    green = {arm: np.array([signal_green(arm, t) for t in times]) for arm in
             [*ARMS, "pedestrians"]}
    together = np.sum([green[arm] for arm in green], axis=0)
    assert together.max() == 1  # never two phases at once
    for arm in ARMS:
        assert 0.12 < green[arm].mean() < 0.25  # each arm a fair share of the cycle
    assert green["east"][: int(GREEN_S / 0.5)].all()


def test_world_is_deterministic_mixed_and_its_vehicles_queue_without_touching():
    first, second = crossroads_world(5, 60.0), crossroads_world(5, 60.0)
    assert [item.path.xy for item in first.objects] == [item.path.xy for item in second.objects]
    classes = Counter(item.class_name for item in first.objects)
    assert {"car", "person"} <= set(classes) and len(classes) >= 4
    states = SyntheticWorld(first).states()
    vehicle = np.array([item.class_name not in ("person", "bicycle") for item in first.objects])
    stopped = 0
    for column in np.flatnonzero(vehicle):
        xy = states.xy[:, column][states.present[:, column]]
        speed = np.hypot(*np.diff(xy, axis=0).T) * first.fps
        stopped += bool((speed < 0.1).sum() >= 20)  # waited 2 s or more somewhere
    assert stopped >= 2  # red lights make queues
    for frame in range(0, len(states.times), 5):
        here = states.present[frame] & vehicle
        xy = states.xy[frame][here]
        gap = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
        np.fill_diagonal(gap, np.inf)
        # Vehicles never drive through each other: followers keep their distance, and
        # opposite lanes pass 3.5 m apart.
        assert len(xy) < 2 or gap.min() >= 3.0


def test_the_site_counts_the_built_origin_destination_matrix():
    world = crossroads_world(1, 40.0)
    scene = SyntheticWorld(world).scene()
    places = load_site_places(find_sites() / "crossroads.yaml").places
    truth = analyse_tracks(scene.ground_truth, places)
    built = crossroads_od(world)
    assert sum(built.values()) > 6
    for origin in ARMS:
        for destination in ARMS:
            assert truth.od[f"{origin}_arm"][f"{destination}_arm"] == built.get(
                (origin, destination), 0), (origin, destination)


def test_sampled_path_interpolates_and_keeps_its_heading_through_a_stop():
    path = SampledPath(1.0, 0.5, ((0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (1.0, 1.0)))
    sample = path.sample(np.array([0.5, 1.25, 1.75, 2.25, 3.0]))
    assert sample.present.tolist() == [False, True, True, True, False]
    assert sample.xy[1].tolist() == [0.5, 0.0]
    assert sample.heading_deg[2] == 0.0  # stopped: still facing +x
    assert sample.heading_deg[3] == 90.0
