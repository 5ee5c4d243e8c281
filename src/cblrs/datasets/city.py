"""A scaled-down city: a street of four planes, 16 cameras, people and cars crossing planes.

The synthetic world of :mod:`cblrs.datasets.synthetic` with several planes, each served by
its own cameras and matcher, so that identities, counts and origin-destination can be
checked *across* planes against a ground truth that knows every object everywhere:

* a straight street along x with a crossing (side streets north and south) on each plane;
* planes 1-2 and 2-3 overlap by 6 m (both planes' cameras see the band where they meet),
  planes 3 and 4 are 16 m apart (a stretch no camera sees: a portal link, 0-30 s transit);
* four cameras on 10 m masts at the corners of each plane, each rendering only its own plane;
* people walk from a side street or an end of the street to another, along the pavements,
  crossing the road on a zebra at a crossing; cars drive the street and turn in and out of
  the side streets; a few people wander near a crossing. Start times are shifted until no
  two objects come closer than a person's (1 m) or a car's (4-8 m) clearance, so nothing
  walks through anything else;
* zones at both street ends and on every side street (the origins and destinations, each on
  its plane), a counting line per plane.

:func:`street_world` builds the :class:`CitySpec` (the world, the planes, which camera serves
which plane, the links, the places, each object's origin and destination by construction);
:func:`city_scenes` projects it into one :class:`~cblrs.datasets.scene.Scene` per plane (its
cameras, its ground truth: objects its cameras have in view on its plane) and a site-wide
ground truth (the union: an object keeps its id on every plane); :func:`city_site_document`
writes the site file (planes, cameras with their plane, places, links) every command reads.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.datasets.scene import Scene
from cblrs.datasets.synthetic import (
    MovingObject,
    RandomWalkPath,
    SyntheticWorld,
    WaypointPath,
    WorldSpec,
    class_size,
)
from cblrs.detections import Detections, Tracks, class_id_of
from cblrs.errors import DatasetError
from cblrs.linking.links import PlaneLink
from cblrs.places import CountingLine, Places, Zone
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.site.cameras import camera_entry
from cblrs.site.schema import SITE_VERSION

FloatArray = NDArray[np.float64]

PLANE_X0 = (0.0, 38.0, 76.0, 136.0)
"""West edge of each plane (metres); planes are 44 m along the street and 30 m across."""
PLANE_WIDTH_M = 44.0
HALF_WIDTH_M = 15.0
PLANE_NAMES = ("west", "market", "station", "east")
CROSSING_X = tuple(x0 + PLANE_WIDTH_M / 2 for x0 in PLANE_X0)
STREET_WEST_M = -8.0
STREET_EAST_M = PLANE_X0[-1] + PLANE_WIDTH_M + 8.0
ARM_OUT_M = 22.0
LANE_Y_M = 2.5
CAR_CORNER_RADIUS_M = 6.0  # turning in and out of the side streets
PAVEMENT_Y_M = (7.0, 10.0)
_IMAGE_SIZE = (1280, 720)
_GRID_S = 0.1

CLEARANCE_M = {("person", "person"): 1.0, ("car", "person"): 4.0, ("car", "car"): 8.0}
"""Closest two objects may come (metres), by class pair: start times are shifted until kept."""


@dataclass(frozen=True)
class CitySpec:
    """A synthetic site of several planes.

    Attributes:
        world: every camera and object (one world frame, metres).
        planes: the planes (ids 1..).
        camera_planes: camera name -> the plane it publishes to.
        links: the hand-overs between planes.
        places: zones (origins and destinations) and counting lines, each on its plane.
        trips: object id -> (origin zone, destination zone) by construction (wanderers have
            none).
    """

    world: WorldSpec
    planes: PlaneSet
    camera_planes: dict[str, int]
    links: tuple[PlaneLink, ...]
    places: Places
    trips: dict[int, tuple[str, str]]

    def cameras_on(self, plane_id: int) -> list[Camera]:
        """The cameras of one plane, in the world's camera order."""
        return [camera for camera in self.world.cameras
                if self.camera_planes[camera.name] == plane_id]

    def true_od(self) -> Counter[tuple[str, str]]:
        """How many objects go from each origin zone to each destination zone."""
        return Counter(self.trips.values())


@dataclass(frozen=True, eq=False)
class CityScenes:
    """A city projected into its cameras.

    Attributes:
        spec: what it was built from.
        planes: plane id -> the plane's scene (its cameras and detections, its ground truth:
            objects its cameras have in view on that plane, ids = object ids).
        ground_truth: the site-wide ground truth: every object on every plane where some of
            that plane's cameras have it in view (an object keeps its id across planes).
        timestamps: (F,) seconds of the frames (shared by every plane).
    """

    spec: CitySpec
    planes: dict[int, Scene]
    ground_truth: Tracks
    timestamps: FloatArray

    @property
    def camera_count(self) -> int:
        """Cameras of the whole site."""
        return len(self.spec.world.cameras)


# ---------------------------------------------------------------------------- building


def street_planes(bits: int = 16) -> PlaneSet:
    """The four planes of the street (ids 1-4, west to east)."""
    return PlaneSet(
        PlaneSpec(index + 1, (x0, -HALF_WIDTH_M), PLANE_WIDTH_M, 2 * HALF_WIDTH_M, bits=bits,
                  name=name)
        for index, (x0, name) in enumerate(zip(PLANE_X0, PLANE_NAMES, strict=True))
    )


def street_cameras() -> tuple[tuple[Camera, int], ...]:
    """Four cameras per plane on 10 m masts just outside its corners, looking across it."""
    cameras = []
    for index, x0 in enumerate(PLANE_X0):
        plane_id = index + 1
        # (corner, mast x, mast y, aimed at x, aimed at y): across the plane, diagonally.
        corners = (("nw", x0 + 2.0, 17.0, x0 + 30.0, -7.0),
                   ("ne", x0 + 42.0, 17.0, x0 + 14.0, -7.0),
                   ("sw", x0 + 2.0, -17.0, x0 + 30.0, 7.0),
                   ("se", x0 + 42.0, -17.0, x0 + 14.0, 7.0))
        for corner, x, y, aim_x, aim_y in corners:
            pan = math.degrees(math.atan2(aim_y - y, aim_x - x))
            distance = math.hypot(aim_x - x, aim_y - y)
            tilt = math.degrees(math.atan2(10.0, distance)) + 8.0
            camera = Camera.from_pose(f"p{plane_id}-{corner}", (x, y, 10.0), pan, tilt, 640.0,
                                      _IMAGE_SIZE)
            cameras.append((camera, plane_id))
    return tuple(cameras)


def street_places() -> Places:
    """Zones at the street's ends and on each side street, a counting line per plane."""
    zones = [
        Zone("west_end", np.array([[0.0, -12.0], [5.0, -12.0], [5.0, 12.0], [0.0, 12.0]]),
             plane_id=1),
        Zone("east_end", np.array([[175.0, -12.0], [180.0, -12.0], [180.0, 12.0],
                                   [175.0, 12.0]]), plane_id=4),
    ]
    lines = []
    for index, x in enumerate(CROSSING_X):
        plane_id = index + 1
        for side, (low, high) in (("north", (11.0, 15.0)), ("south", (-15.0, -11.0))):
            polygon = np.array([[x - 6.0, low], [x + 6.0, low], [x + 6.0, high], [x - 6.0, high]])
            zones.append(Zone(f"{side}_{plane_id}", polygon, plane_id=plane_id))
        lines.append(CountingLine(f"line_{plane_id}", np.array([x + 10.0, -12.0]),
                                  np.array([x + 10.0, 12.0]), plane_id=plane_id))
    return Places(tuple(zones), tuple(lines))


def street_links(planes: PlaneSet) -> tuple[PlaneLink, ...]:
    """Planes 1-2 and 2-3 overlap; 3 and 4 are joined by portals at the facing edges."""
    third, fourth = planes.by_id(3), planes.by_id(4)
    east_of_third = third.origin[0] + third.width
    west_of_fourth = fourth.origin[0]
    portals = (
        [[east_of_third - 6.0, -HALF_WIDTH_M], [east_of_third, -HALF_WIDTH_M],
         [east_of_third, HALF_WIDTH_M], [east_of_third - 6.0, HALF_WIDTH_M]],
        [[west_of_fourth, -HALF_WIDTH_M], [west_of_fourth + 6.0, -HALF_WIDTH_M],
         [west_of_fourth + 6.0, HALF_WIDTH_M], [west_of_fourth, HALF_WIDTH_M]],
    )
    return (
        PlaneLink.overlap(planes.by_id(1), planes.by_id(2)),
        PlaneLink.overlap(planes.by_id(2), planes.by_id(3)),
        PlaneLink.through_portals((3, 4), portals, (0.0, 30.0)),
    )


_ENDPOINTS = ("west_end", "east_end", *(f"{side}_{index + 1}" for index in range(4)
                                        for side in ("north", "south")))


def _endpoint_x(name: str) -> float:
    if name == "west_end":
        return STREET_WEST_M
    if name == "east_end":
        return STREET_EAST_M
    return CROSSING_X[int(name.split("_")[1]) - 1]


def _walk(origin: str, destination: str, rng: np.random.Generator) -> list[tuple[float, float]]:
    """A person's waypoints from ``origin`` to ``destination`` along the pavements."""

    def pavement(side: int) -> float:
        return side * float(rng.uniform(*PAVEMENT_Y_M))

    def arm_offset() -> float:
        return float(rng.choice([-1.0, 1.0]) * rng.uniform(3.5, 5.0))

    origin_side = 1 if origin.startswith("north") else -1 if origin.startswith("south") else (
        int(rng.choice([-1, 1])))
    destination_side = 1 if destination.startswith("north") else (
        -1 if destination.startswith("south") else origin_side)
    y_origin = pavement(origin_side)
    points: list[tuple[float, float]] = []
    if origin.endswith("_end"):
        points.append((_endpoint_x(origin), y_origin))
    else:
        x = _endpoint_x(origin) + arm_offset()
        points += [(x, origin_side * ARM_OUT_M), (x, y_origin)]
    if destination_side != origin_side:
        y_destination = pavement(destination_side)
        cross_at = _endpoint_x(destination if not destination.endswith("_end") else origin)
        cross_at += float(rng.uniform(-1.5, 1.5))
        points += [(cross_at, y_origin), (cross_at, y_destination)]
    else:
        y_destination = y_origin
    if destination.endswith("_end"):
        points.append((_endpoint_x(destination), y_destination))
    else:
        x = _endpoint_x(destination) + arm_offset()
        points += [(x, y_destination), (x, destination_side * ARM_OUT_M)]
    return points


def _drive(origin: str, destination: str) -> list[tuple[float, float]]:
    """A car's waypoints: in on ``origin``'s lane, along the street, out at ``destination``."""
    eastbound = _endpoint_x(destination) > _endpoint_x(origin)
    lane = -LANE_Y_M if eastbound else LANE_Y_M
    points: list[tuple[float, float]] = []
    if origin.endswith("_end"):
        points.append((_endpoint_x(origin) - (2.0 if eastbound else -2.0), lane))
    else:
        side = 1 if origin.startswith("north") else -1
        # Drive on the right: down the west half of a north arm, up the east half of a south one.
        x = _endpoint_x(origin) - side * 2.0
        points += [(x, side * (ARM_OUT_M + 3.0)), (x, lane)]
    if destination.endswith("_end"):
        points.append((_endpoint_x(destination) + (2.0 if eastbound else -2.0), lane))
    else:
        side = 1 if destination.startswith("north") else -1
        x = _endpoint_x(destination) + side * 2.0
        points += [(x, lane), (x, side * (ARM_OUT_M + 3.0))]
    # A car cannot turn a corner on the spot: it follows an arc (the fusion tracker's
    # turning-radius rule would rightly split a track that did).
    return _round_corners(points, CAR_CORNER_RADIUS_M)


def _round_corners(points: list[tuple[float, float]],
                   radius_m: float) -> list[tuple[float, float]]:
    """The polyline with each corner replaced by a circular arc of ``radius_m`` (smaller
    where a leg is too short for it); repeated points and straight-through vertices go."""
    kept = [np.asarray(points[0], np.float64)]
    for point in points[1:]:
        if np.hypot(*(np.asarray(point) - kept[-1])) > 1e-6:
            kept.append(np.asarray(point, np.float64))
    rounded = [kept[0]]
    for before, corner, after in zip(kept, kept[1:], kept[2:], strict=False):
        leg_in, leg_out = corner - before, after - corner
        length_in, length_out = np.hypot(*leg_in), np.hypot(*leg_out)
        u, v = leg_in / length_in, leg_out / length_out
        turn = math.acos(float(np.clip(u @ v, -1.0, 1.0)))
        if turn < 1e-3 or turn > math.pi - 1e-3:
            rounded.append(corner)  # straight on (or a U-turn, which no trip makes)
            continue
        tangent = min(radius_m * math.tan(turn / 2), length_in / 2, length_out / 2)
        radius = tangent / math.tan(turn / 2)
        left = 1.0 if u[0] * v[1] - u[1] * v[0] > 0 else -1.0
        centre = corner - u * tangent + left * radius * np.array([-u[1], u[0]])
        first = math.atan2(*(corner - u * tangent - centre)[::-1])
        steps = max(2, math.ceil(turn / math.radians(10.0)))
        for angle in first + left * turn * np.linspace(0.0, 1.0, steps + 1):
            rounded.append(centre + radius * np.array([math.cos(angle), math.sin(angle)]))
    rounded.append(kept[-1])
    return [(float(x), float(y)) for x, y in rounded]


def _length(points: list[tuple[float, float]]) -> float:
    array = np.asarray(points)
    return float(np.hypot(*np.diff(array, axis=0).T).sum())


def street_world(
    seed: int = 0,
    people: int = 40,
    cars: int = 12,
    wanderers: int = 4,
    spawn_s: float = 40.0,
    max_trip_m: float = 90.0,
    cross_fraction: float = 0.8,
    fps: float = 10.0,
    bits: int = 16,
) -> CitySpec:
    """The street: four planes, 16 cameras, people and cars crossing planes.

    Args:
        seed: seed of every choice (trips, speeds, sizes, start times).
        people: people walking from one endpoint (street end or side street) to another.
        cars: cars driving from one endpoint to another (never to the same crossing).
        wanderers: people wandering near a crossing (inside one plane).
        spawn_s: trips start within this many seconds (later when clearance needs it).
        max_trip_m: no trip is longer than this (metres along its path).
        cross_fraction: the share of trips that end at least 30 m along the street from
            where they start (on another plane); the others stay near their crossing.
        fps: frame rate.
        bits: bits per colour channel of the planes.

    Returns:
        The :class:`CitySpec`; the duration is long enough for the last trip to end.
    """
    if people < 0 or cars < 0 or wanderers < 0 or spawn_s < 0 or max_trip_m <= 0:
        raise DatasetError("people, cars, wanderers and spawn_s must be >= 0, max_trip_m > 0.")
    rng = np.random.default_rng(seed)
    planes = street_planes(bits)
    # Long enough for the slowest walker on the longest trip after the longest wait.
    grid = np.arange(0.0, spawn_s + max_trip_m / 1.1 + 120.0 + 40.0, _GRID_S)
    placed: dict[str, list[FloatArray]] = {"person": [], "car": []}
    objects: list[MovingObject] = []
    trips: dict[int, tuple[str, str]] = {}
    end_s = 0.0

    def fits(class_name: str, xy: FloatArray) -> bool:
        present = np.isfinite(xy[:, 0])
        for other_class, others in placed.items():
            if not others:
                continue
            key = (min(class_name, other_class), max(class_name, other_class))
            clearance = CLEARANCE_M[key]
            other = np.stack(others)[:, present]  # (K, T', 2)
            with np.errstate(invalid="ignore"):
                gap = np.hypot(*(other - xy[present]).transpose(2, 0, 1))
            if (gap < clearance).any():
                return False
        return True

    def place(object_id: int, class_name: str, make: Any, start: float,
              lifetime_s: float | None = None) -> float | None:
        for _ in range(240):
            path = make(start)
            if lifetime_s is None:
                xy = path.sample(grid).xy
            else:
                # A random walk integrates up to the last time asked: ask only its own life.
                alive = (grid >= start - _GRID_S) & (grid <= start + lifetime_s + _GRID_S)
                xy = np.full((len(grid), 2), np.nan)
                xy[alive] = path.sample(grid[alive]).xy
            if fits(class_name, xy):
                placed[class_name].append(xy)
                objects.append(MovingObject(object_id, class_name, class_size(class_name, rng),
                                            path))
                return start
            start += 0.5
        return None

    kinds = ["person"] * people + ["car"] * cars
    order = rng.permutation(len(kinds))
    next_id = 1
    for index in order.tolist():
        class_name = kinds[index]
        # Most trips end on another plane than they start (what the linking is for).
        across = bool(rng.random() < cross_fraction)
        for _ in range(200):
            origin, destination = rng.choice(_ENDPOINTS, size=2, replace=False).tolist()
            gap = abs(_endpoint_x(origin) - _endpoint_x(destination))
            # A street end is 30 m from its plane's crossing: across means beyond that.
            if (class_name == "car" and gap < 10) or (across and gap <= 30) or (
                    not across and gap > 30):
                continue
            points = _walk(origin, destination, rng) if class_name == "person" else _drive(
                origin, destination)
            if _length(points) <= max_trip_m:
                break
        else:
            continue
        speed = float(rng.uniform(1.1, 1.6) if class_name == "person" else rng.uniform(6.0, 9.0))
        start = float(rng.uniform(0.0, spawn_s))
        chosen = place(next_id, class_name,
                       lambda start, points=points, speed=speed: WaypointPath(
                           tuple(points), speed, start), start)
        if chosen is not None:
            trips[next_id] = (origin, destination)
            end_s = max(end_s, chosen + _length(points) / speed)
            next_id += 1
    for index in range(wanderers):
        plane = planes[index % len(planes)]
        x = CROSSING_X[index % len(planes)]
        area = (x - 9.0, 5.5, x + 9.0, 10.5) if index % 2 == 0 else (x - 9.0, -10.5, x + 9.0,
                                                                     -5.5)
        walk_seed = int(rng.integers(2**31))
        speed = float(rng.uniform(0.8, 1.2))
        start = float(rng.uniform(0.0, spawn_s / 2))
        stay = float(rng.uniform(20.0, 40.0))
        centre = ((area[0] + area[2]) / 2, (area[1] + area[3]) / 2)
        chosen = place(next_id, "person",
                       lambda start, area=area, walk_seed=walk_seed, speed=speed, stay=stay,
                       centre=centre: RandomWalkPath(centre, area, speed, walk_seed,
                                                     start_s=start, end_s=start + stay), start,
                       stay)
        if chosen is not None and plane.contains(np.array([centre])).all():
            end_s = max(end_s, chosen + stay)
            next_id += 1
    cameras = street_cameras()
    world = WorldSpec(
        name="street",
        cameras=tuple(camera for camera, _ in cameras),
        objects=tuple(objects),
        area=(STREET_WEST_M - 5.0, -ARM_OUT_M - 5.0, STREET_EAST_M + 5.0, ARM_OUT_M + 5.0),
        duration_s=end_s + 1.0,
        fps=fps,
        bits=bits,
    )
    return CitySpec(
        world=world,
        planes=planes,
        camera_planes={camera.name: plane_id for camera, plane_id in cameras},
        links=street_links(planes),
        places=street_places(),
        trips=trips,
    )


# ---------------------------------------------------------------------------- projecting


def city_scenes(spec: CitySpec) -> CityScenes:
    """Project every object into every camera: one scene per plane and a site-wide truth.

    A plane's scene holds its cameras' boxes (boxes of objects off its plane included: their
    colour says "no location", as on a real camera) and its ground truth: the objects that
    one of its cameras has in view (occluded or not) while they stand on the plane.
    """
    world = SyntheticWorld(spec.world)
    states = world.states()
    frames, count = states.present.shape
    class_ids = np.array([class_id_of(item.class_name) for item in spec.world.objects], np.int64)
    object_ids = np.array([item.object_id for item in spec.world.objects], np.int64)
    boxes = {camera.name: world.camera_boxes(states, camera) for camera in spec.world.cameras}
    flat_xy = np.nan_to_num(states.xy, nan=np.inf).reshape(-1, 2)
    scenes: dict[int, Scene] = {}
    truth_parts = []
    for plane in spec.planes:
        cameras = spec.cameras_on(plane.plane_id)
        seen = np.zeros((frames, count), dtype=bool)
        for camera in cameras:
            seen |= boxes[camera.name][2]
        seen &= plane.contains(flat_xy).reshape(frames, count)
        frame_index, column = np.nonzero(seen)
        truth = Tracks(
            frame=frame_index.astype(np.int64),
            timestamp=states.times[frame_index],
            track_id=object_ids[column],
            world_xy=states.xy[frame_index, column],
            class_id=class_ids[column],
        )
        truth_parts.append(truth)
        detections = []
        for frame in range(frames):
            row = []
            for camera in cameras:
                xyxy, detected, _ = boxes[camera.name]
                keep = detected[frame]
                row.append(Detections(xyxy=xyxy[frame][keep], confidence=np.ones(int(keep.sum())),
                                      class_id=class_ids[keep], object_id=object_ids[keep]))
            detections.append(row)
        scenes[plane.plane_id] = Scene(
            name=f"{spec.world.name}-{plane.plane_id}",
            cameras=cameras,
            frames=np.arange(frames, dtype=np.int64),
            timestamps=states.times,
            detections=detections,
            ground_truth=truth,
            plane=plane,
        )
    return CityScenes(spec, scenes, site_truth(truth_parts), states.times)


def site_truth(per_plane: list[Tracks]) -> Tracks:
    """The site-wide ground truth from the planes' truths: one row per (frame, object).

    Where two planes overlap an object is in both; the positions are the same (one world).
    """
    rows = Tracks.concatenate(per_plane)
    if len(rows) == 0:
        return rows
    keys = np.stack([rows.frame, rows.track_id], axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    rows = rows[np.sort(first)]
    order = np.lexsort((rows.track_id, rows.frame))
    return rows[order]


def city_site_document(spec: CitySpec, name: str = "street") -> dict[str, Any]:
    """The site file of a city: planes, cameras (inline geometry and plane), places, links."""
    cameras = []
    for camera in spec.world.cameras:
        entry = camera_entry(camera)
        entry["plane"] = spec.camera_planes[camera.name]
        cameras.append(entry)
    return {
        "version": SITE_VERSION,
        "name": name,
        "planes": [
            {"id": plane.plane_id, "name": plane.name, "origin": list(plane.origin),
             "size": [plane.width, plane.length], "bits": plane.bits, "height": plane.height}
            for plane in spec.planes
        ],
        "cameras": cameras,
        "places": spec.places.to_dict(),
        "links": [link.to_dict() for link in spec.links],
    }
