"""The synthetic city: four planes, 16 cameras, objects crossing planes, a site file."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from cblrs.analytics import AnalyticsConfig
from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets.city import (
    CLEARANCE_M,
    city_scenes,
    city_site_document,
    street_world,
)
from cblrs.errors import DatasetError
from cblrs.pipeline import render_scene_references
from cblrs.site import load_site, save_document

SMALL = {"people": 10, "cars": 4, "wanderers": 1, "spawn_s": 6.0, "max_trip_m": 90.0}


@pytest.fixture(scope="module")
def city():
    return city_scenes(street_world(seed=2, **SMALL))  # a world with crossings of every link


def test_four_planes_sixteen_cameras_two_overlaps_and_a_portal(city):
    spec = city.spec
    assert spec.planes.ids == [1, 2, 3, 4] and city.camera_count == 16
    assert Counter(spec.camera_planes.values()) == {1: 4, 2: 4, 3: 4, 4: 4}
    assert [(link.planes, link.portal) for link in spec.links] == [
        ((1, 2), False), ((2, 3), False), ((3, 4), True)]
    for plane_id, scene in city.planes.items():
        assert [camera.name for camera in scene.cameras] == [
            camera.name for camera in spec.cameras_on(plane_id)]
        assert scene.plane == spec.planes.by_id(plane_id)


def test_each_plane_sees_its_own_ground_and_the_site_truth_is_their_union(city):
    rows = set()
    for plane_id, scene in city.planes.items():
        truth = scene.ground_truth
        assert len(truth) and spec_plane(city, plane_id).contains(truth.world_xy).all()
        rows |= set(zip(truth.frame.tolist(), truth.track_id.tolist(), strict=True))
    site = city.ground_truth
    keys = list(zip(site.frame.tolist(), site.track_id.tolist(), strict=True))
    assert len(keys) == len(set(keys)) == len(rows) and set(keys) == rows
    # Objects that cross planes, on both sides of the overlaps and of the portal.
    planes_of: dict[int, set[int]] = {}
    for plane_id, scene in city.planes.items():
        for object_id in np.unique(scene.ground_truth.track_id).tolist():
            planes_of.setdefault(object_id, set()).add(plane_id)
    crossing = [planes for planes in planes_of.values() if len(planes) > 1]
    assert len(crossing) >= len(planes_of) // 2
    assert any({3, 4} <= planes for planes in crossing)


def spec_plane(city, plane_id):
    return city.spec.planes.by_id(plane_id)


def test_nothing_walks_through_anything_else(city):
    from cblrs.datasets.synthetic import SyntheticWorld

    states = SyntheticWorld(city.spec.world).states()
    classes = [item.class_name for item in city.spec.world.objects]
    xy = states.xy
    for first in range(len(classes)):
        for second in range(first + 1, len(classes)):
            clearance = CLEARANCE_M[tuple(sorted((classes[first], classes[second])))]
            with np.errstate(invalid="ignore"):
                gap = np.hypot(*(xy[:, first] - xy[:, second]).T)
            # Sampled at the frames (0.1 s); placement checked on the same grid.
            assert not (gap < clearance - 1e-6).any(), (first, second, np.nanmin(gap))


def test_the_truths_origin_destination_is_the_built_one(city):
    # Lives must span the portal's unseen stretch: lost only after its longest transit.
    result = analyse_tracks(city.ground_truth, city.spec.places, AnalyticsConfig(lost_after_s=31))
    counted = Counter({(origin, destination): value for origin, row in result.od.items()
                       for destination, value in row.items() if value})
    assert counted == city.spec.true_od() and sum(counted.values()) >= 10


def test_the_site_file_reproduces_the_world(city, tmp_path):
    path = save_document(city_site_document(city.spec), tmp_path / "street.yaml")
    site = load_site(path)
    assert site.planes == city.spec.planes and len(site.links) == 3
    assert [link.to_dict() for link in site.links] == [link.to_dict() for link in city.spec.links]
    assert site.places.to_dict() == city.spec.places.to_dict()
    scene = city.planes[3]
    expected = render_scene_references(scene)
    for camera, reference in zip(scene.cameras, expected, strict=True):
        assert site.camera_plane(camera.name) == 3
        np.testing.assert_array_equal(site.render_reference(camera.name).pixels,
                                      reference.pixels)


def test_same_seed_same_world_and_bad_settings_are_refused():
    first, second = street_world(seed=3, **SMALL), street_world(seed=3, **SMALL)
    assert first.trips == second.trips
    times = np.arange(0, 30, 0.5)
    for a, b in zip(first.world.objects, second.world.objects, strict=True):
        np.testing.assert_array_equal(a.path.sample(times).xy, b.path.sample(times).xy)
    with pytest.raises(DatasetError, match="must be >= 0"):
        street_world(people=-1)
