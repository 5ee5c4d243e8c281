"""A synthetic roundabout with traffic: cars enter on one arm and leave on another.

The demo's ``roundabout`` preset holds one car driving one lap (the paper's hand-over case),
which has no entries or exits to count. This world is built for origin-destination counts:
four arms (east, north, west, south), right-hand traffic, the ring driven counter-clockwise,
and cars whose entry and exit arms are drawn from a seed — so the true entry -> exit matrix is
known by construction (:func:`traffic_od`) and can be compared with what the analytics count
from ground-truth or tracked positions. Four cameras on 10 m masts at the corners look at
the centre; a monument on the central island hides the far side of the ring from each.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from cblrs.camera import Camera
from cblrs.datasets.presets import roundabout_markings
from cblrs.datasets.scene import Scene
from cblrs.datasets.synthetic import (
    MovingObject,
    Structure,
    SyntheticWorld,
    WaypointPath,
    WorldSpec,
    class_size,
)

ARMS = {"east": 0.0, "north": 90.0, "west": 180.0, "south": 270.0}
"""Arm name -> direction of the arm from the centre, degrees counter-clockwise from +x."""

RING_RADIUS_M = 12.0
LANE_OFFSET_M = 2.0
ARM_LENGTH_M = 31.0
MIN_GAP_M = 8.0
ENTRY_RADIUS_M = 15.0
"""Radius of the curves from an arm's lane onto the ring and off it, metres.

The low end of the entry radii of urban single-lane roundabouts, 15 to 30 m (50 to 100 ft;
NCHRP Report 672, *Roundabouts: An Informational Guide*, 2nd ed., 2010, section 6.5.4
"Entry curves"), and well above a car's minimum turning radius (a turning circle of 10-12 m
kerb to kerb, about 5-6 m radius; the tracker's ``class_turn_radius_m`` holds cars to 5 m).
Until issue 19's second pass a car turned about 80 degrees at one waypoint where the lane
met the ring, which no car can do.
"""
_IMAGE_SIZE = (1280, 720)


def _arm_point(angle_deg: float, along_m: float, offset_m: float) -> tuple[float, float]:
    """A point ``along_m`` out along an arm and ``offset_m`` to its counter-clockwise side."""
    angle = math.radians(angle_deg)
    return (
        along_m * math.cos(angle) - offset_m * math.sin(angle),
        along_m * math.sin(angle) + offset_m * math.cos(angle),
    )


def _entry_curve(angle_deg: float) -> list[tuple[float, float]]:
    """The entry curve of the arm at ``angle_deg``: from the inbound lane onto the ring.

    A circle of radius ENTRY_RADIUS_M tangent to the inbound lane (offset LANE_OFFSET_M,
    driven towards the centre) and, from outside, to the ring (RING_RADIUS_M): a right turn
    onto the counter-clockwise ring. Returns points from where the lane stops being straight
    to where the car joins the ring, about every 5 degrees of heading.
    """
    radius, offset = ENTRY_RADIUS_M, LANE_OFFSET_M
    # In the arm's frame (arm along +x): centre (cx, offset + radius), at RING_RADIUS_M +
    # radius from the roundabout's centre.
    centre_y = offset + radius
    centre_x = math.sqrt((RING_RADIUS_M + radius) ** 2 - centre_y**2)
    joins = math.atan2(centre_y, centre_x)  # the ring's angle where the curve meets it
    # Round the curve's centre from straight below it (on the lane) to facing the
    # roundabout's centre (on the ring), clockwise: the car turns right by 90 - joins degrees.
    first, last = -0.5 * math.pi, joins - math.pi
    steps = max(2, int(math.degrees(first - last) / 5.0) + 1)
    local = [
        (centre_x + radius * math.cos(turn), centre_y + radius * math.sin(turn))
        for turn in np.linspace(first, last, steps).tolist()
    ]
    rotation = math.radians(angle_deg)
    cos, sin = math.cos(rotation), math.sin(rotation)
    return [(x * cos - y * sin, x * sin + y * cos) for x, y in local]


def _joins_ring_deg() -> float:
    """How far round the ring (degrees from the arm's axis) the entry curve meets it."""
    centre_y = LANE_OFFSET_M + ENTRY_RADIUS_M
    centre_x = math.sqrt((RING_RADIUS_M + ENTRY_RADIUS_M) ** 2 - centre_y**2)
    return math.degrees(math.atan2(centre_y, centre_x))


def car_path(origin: str, destination: str, speed: float, start_s: float) -> WaypointPath:
    """In on ``origin``'s inbound lane, counter-clockwise round the ring, out on
    ``destination``'s outbound lane.

    Entry and exit are curves of radius ENTRY_RADIUS_M tangent to the lane and to the ring
    (:func:`_entry_curve`; an exit is an entry mirrored about its arm's axis), so a car
    never turns tighter than it can.
    """
    entry_arm, exit_arm = ARMS[origin], ARMS[destination]
    # Inbound lanes lie counter-clockwise of the arm's axis (driving on the right, towards the
    # centre), outbound lanes clockwise of it.
    joins = _joins_ring_deg()
    start_angle = entry_arm + joins
    end_angle = exit_arm - joins
    sweep = (end_angle - start_angle) % 360.0
    arc = [
        (
            RING_RADIUS_M * math.cos(math.radians(start_angle + step)),
            RING_RADIUS_M * math.sin(math.radians(start_angle + step)),
        )
        for step in np.linspace(0.0, sweep, max(2, int(sweep / 8.0) + 1)).tolist()
    ]
    entry = _entry_curve(entry_arm)
    # The exit curve: the exit arm's entry curve mirrored about the arm's axis, driven
    # backwards (from the ring out onto the outbound lane).
    axis = math.radians(exit_arm)
    mirror = np.array(
        [[math.cos(2 * axis), math.sin(2 * axis)], [math.sin(2 * axis), -math.cos(2 * axis)]]
    )
    exit_curve = [tuple(mirror @ np.asarray(point)) for point in reversed(_entry_curve(exit_arm))]
    points = (
        _arm_point(entry_arm, ARM_LENGTH_M, LANE_OFFSET_M),
        *entry,
        *arc[1:-1],
        *exit_curve,
        _arm_point(exit_arm, ARM_LENGTH_M, -LANE_OFFSET_M),
    )
    return WaypointPath(tuple((float(x), float(y)) for x, y in points), speed, start_s)


def roundabout_traffic_world(
    seed: int = 0, duration_s: float | None = None, fps: float | None = None, cars: int = 30
) -> WorldSpec:
    """Cars through a four-arm roundabout, one every ~3 s, seeded origins and destinations.

    Args:
        seed: seed of the arms, speeds, sizes and start times.
        duration_s: length in seconds (default: long enough for the last car to leave).
        fps: frame rate (default 10).
        cars: how many cars.
    """
    rng = np.random.default_rng(seed)
    names = list(ARMS)
    objects: list[MovingObject] = []
    start = 0.0
    grid = np.arange(0.0, cars * 6.0 + 60.0, 0.1)
    occupied: list[np.ndarray] = []  # (T, 2) positions of the cars placed so far
    for index in range(cars):
        origin = names[int(rng.integers(4))]
        destination = names[(names.index(origin) + int(rng.integers(1, 4))) % 4]
        speed = float(rng.uniform(6.0, 8.0))
        # A car waits at its entry until it keeps MIN_GAP_M from every other car all the way
        # (cars do not drive through each other, and a tracker could not tell them apart).
        while True:
            path = car_path(origin, destination, speed, start)
            xy = path.sample(grid).xy
            if all(not (np.hypot(*(xy - other).T) < MIN_GAP_M).any() for other in occupied):
                break
            start += 0.5
        occupied.append(xy)
        objects.append(MovingObject(index + 1, "car", class_size("car", rng), path))
        start += float(rng.uniform(2.0, 4.0))
    cameras = tuple(
        Camera.from_pose(
            name, (x, y, 10.0), math.degrees(math.atan2(-y, -x)), 20.0, 700.0, _IMAGE_SIZE
        )
        for name, x, y in (
            ("NE", 27.0, 27.0),
            ("NW", -27.0, 27.0),
            ("SW", -27.0, -27.0),
            ("SE", 27.0, -27.0),
        )
    )
    monument = (Structure((0.0, 0.0), (8.0, 8.0, 6.0), 45.0, "monument"),)
    return WorldSpec(
        name="roundabout-traffic",
        cameras=cameras,
        objects=tuple(objects),
        area=(-32.0, -32.0, 32.0, 32.0),
        duration_s=start + 16.0 if duration_s is None else duration_s,
        fps=10.0 if fps is None else fps,
        structures=monument,
        markings=roundabout_markings(RING_RADIUS_M),
    )


def traffic_od(world: WorldSpec) -> Counter[tuple[str, str]]:
    """The true (origin arm, destination arm) of every car of a traffic world."""
    od: Counter[tuple[str, str]] = Counter()
    for item in world.objects:
        path = item.path
        assert isinstance(path, WaypointPath)
        first, last = np.asarray(path.points[0]), np.asarray(path.points[-1])
        od[(_arm_of(first), _arm_of(last))] += 1
    return od


def _arm_of(point: np.ndarray) -> str:
    angle = math.degrees(math.atan2(point[1], point[0])) % 360.0
    return min(ARMS, key=lambda name: abs((angle - ARMS[name] + 180.0) % 360.0 - 180.0))


def make_traffic_scene(seed: int = 0, duration_s: float | None = None) -> Scene:
    """The :class:`Scene` of :func:`roundabout_traffic_world`."""
    return SyntheticWorld(roundabout_traffic_world(seed, duration_s)).scene()
