"""The roundabout traffic world: cars drive paths a car can drive, and the scene is unchanged."""

import math

import numpy as np
import pytest

from cblrs.datasets.traffic import (
    ARMS,
    ENTRY_RADIUS_M,
    LANE_OFFSET_M,
    RING_RADIUS_M,
    car_path,
    roundabout_traffic_world,
    traffic_od,
)

# The tracker's smallest turning radius of a car (class_turn_radius_m): a path must not be
# tighter than a car can turn.
CAR_TURN_RADIUS_M = 5.0


def _curvature_radii(points: np.ndarray) -> np.ndarray:
    """Radius of the circle through each three consecutive waypoints (inf when straight)."""
    a, b, c = points[:-2], points[1:-1], points[2:]
    ab, bc, ca = (
        np.linalg.norm(b - a, axis=1),
        np.linalg.norm(c - b, axis=1),
        np.linalg.norm(a - c, axis=1),
    )
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore"):
        return np.where(cross > 1e-9, ab * bc * ca / (2.0 * cross), np.inf)


@pytest.mark.parametrize("origin", list(ARMS))
@pytest.mark.parametrize("turn", [1, 2, 3])
def test_every_path_turns_no_tighter_than_the_ring_or_its_entry_curve(origin, turn):
    names = list(ARMS)
    destination = names[(names.index(origin) + turn) % 4]
    points = np.asarray(car_path(origin, destination, 7.0, 0.0).points)
    radii = _curvature_radii(points)
    # Waypoints sampled on circles of RING_RADIUS_M and ENTRY_RADIUS_M; where they meet, the
    # circle through three points is a little tighter than either but never a car's limit.
    assert radii.min() > 0.8 * min(RING_RADIUS_M, ENTRY_RADIUS_M)
    assert radii.min() > 2 * CAR_TURN_RADIUS_M
    # Heading never jumps by more than a few degrees from one waypoint to the next (the old
    # world turned about 80 degrees at the waypoint where the lane met the ring).
    steps = np.diff(points, axis=0)
    heading = np.unwrap(np.arctan2(steps[:, 1], steps[:, 0]))
    assert np.degrees(np.abs(np.diff(heading))).max() < 10.0


def test_entry_curve_is_tangent_to_the_lane_and_to_the_ring():
    points = np.asarray(car_path("east", "west", 7.0, 0.0).points)
    # The lane is straight at offset LANE_OFFSET_M up to where the curve starts ...
    assert points[0] == pytest.approx((31.0, LANE_OFFSET_M))
    assert points[1][1] == pytest.approx(LANE_OFFSET_M)
    # ... and the curve ends on the ring, moving along it (square to its radius).
    radii = np.hypot(points[:, 0], points[:, 1])
    on_ring = np.flatnonzero(np.isclose(radii, RING_RADIUS_M))
    first = on_ring[0]
    arriving = points[first] - points[first - 1]
    cosine = abs(arriving @ points[first]) / (np.linalg.norm(arriving) * RING_RADIUS_M)
    assert cosine < math.sin(math.radians(6.0))


def test_the_scene_keeps_its_arms_and_origin_destination_truth():
    world = roundabout_traffic_world(0, cars=30)
    assert len(world.objects) == 30
    od = traffic_od(world)
    assert sum(od.values()) == 30
    assert all(origin != destination for origin, destination in od)
    for item in world.objects:
        first, last = np.asarray(item.path.points[0]), np.asarray(item.path.points[-1])
        assert np.hypot(*first) == pytest.approx(math.hypot(31.0, LANE_OFFSET_M))
        assert np.hypot(*last) == pytest.approx(math.hypot(31.0, LANE_OFFSET_M))
