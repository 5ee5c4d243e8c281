"""A synthetic signalised crossroads: queues, opposite lanes, mixed classes, pedestrians.

A second traffic world, built to check what is tuned on the roundabout
(:mod:`cblrs.datasets.traffic`) on a scene it was not tuned on. Four arms (east, north, west,
south) meet at a junction controlled by a traffic light with split phases: each arm's traffic
has green in turn (straight, left and right together), then all vehicles stop while
pedestrians cross every arm at once (a scramble phase). Right-hand traffic; each arm has one
inbound and one outbound lane whose centres are 3.5 m apart, and a bicycle lane on each side.

Vehicles (cars, buses, trucks; bicycles on their lanes, straight on or turning right) arrive
on each arm at random, queue at the stop line while their light is red (keeping a gap to the
one ahead), cross and leave on the arm they chose. Pedestrians walk along the pavements,
wait at the kerb and cross during the scramble. The motion is simulated on a 0.1 s grid and
stored as :class:`~cblrs.datasets.paths.SampledPath`, so the scene is exact and deterministic
for a seed; :func:`crossroads_od` is the true origin -> destination matrix of the vehicles.
Four cameras on 10 m masts at the corners look at the junction.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from cblrs.camera import Camera
from cblrs.datasets.paths import SampledPath
from cblrs.datasets.scene import Scene
from cblrs.datasets.synthetic import MovingObject, SyntheticWorld, WorldSpec, class_size

ARMS = {"east": 0.0, "north": 90.0, "west": 180.0, "south": 270.0}
"""Arm name -> direction of the arm from the centre, degrees counter-clockwise from +x."""

LANE_OFFSET_M = 1.75
BICYCLE_OFFSET_M = 4.2
PAVEMENT_OFFSET_M = 8.5
STOP_LINE_M = 11.0
JUNCTION_M = 9.0
ARM_LENGTH_M = 45.0
GREEN_S = 10.0
CLEARANCE_S = 3.0
PEDESTRIAN_S = 10.0
STEP_S = 0.1
_IMAGE_SIZE = (1280, 720)
_CLASS_SHARE = (("car", 0.7), ("truck", 0.1), ("bus", 0.07), ("bicycle", 0.13))
_DESIRED_SPEED = {"car": (8.0, 11.0), "truck": (6.5, 8.5), "bus": (6.0, 8.0),
                  "bicycle": (4.0, 5.5)}
_ACCELERATION = {"car": 2.5, "truck": 1.2, "bus": 1.2, "bicycle": 1.2}
_BRAKING = 3.0


def _point(angle_deg: float, along_m: float, offset_m: float) -> np.ndarray:
    """A point ``along_m`` out along an arm and ``offset_m`` to its counter-clockwise side."""
    angle = math.radians(angle_deg)
    return np.array([along_m * math.cos(angle) - offset_m * math.sin(angle),
                     along_m * math.sin(angle) + offset_m * math.cos(angle)])


def _route(origin: str, destination: str, offset_m: float) -> np.ndarray:
    """(K, 2) polyline: in on ``origin``'s inbound lane, out on ``destination``'s outbound."""
    entry = [_point(ARMS[origin], along, offset_m) for along in (ARM_LENGTH_M, JUNCTION_M)]
    leave = [_point(ARMS[destination], along, -offset_m)
             for along in (JUNCTION_M, ARM_LENGTH_M)]
    start, end = entry[-1], leave[0]
    heading_in = -np.array([math.cos(math.radians(ARMS[origin])),
                            math.sin(math.radians(ARMS[origin]))])
    heading_out = np.array([math.cos(math.radians(ARMS[destination])),
                            math.sin(math.radians(ARMS[destination]))])
    # Turn through the junction on a quadratic Bezier curve whose control point is where the
    # two lanes' lines meet (straight on: the midpoint).
    matrix = np.column_stack([heading_in, -heading_out])
    if abs(np.linalg.det(matrix)) < 1e-9:
        control = (start + end) / 2
    else:
        along = np.linalg.solve(matrix, end - start)
        control = start + along[0] * heading_in
    steps = np.linspace(0.0, 1.0, 12)[1:-1, None]
    curve = (1 - steps) ** 2 * start + 2 * (1 - steps) * steps * control + steps**2 * end
    return np.vstack([*entry, *curve, *leave])


@dataclass
class _Mover:
    route: np.ndarray  # (K, 2)
    cumulative: np.ndarray  # (K,) arc length
    stop_s: float  # arc length of the stop line (or kerb)
    length: float
    desired: float
    acceleration: float
    arrive: float
    arm: str  # whose signal it obeys
    kind: str  # "vehicle", "bicycle" or "pedestrian"
    s: float = 0.0
    speed: float = -1.0  # below zero: arrives at its desired speed
    committed: bool = False
    done: bool = False

    def position(self, s: float | None = None) -> np.ndarray:
        s = self.s if s is None else s
        return np.array([np.interp(s, self.cumulative, self.route[:, 0]),
                         np.interp(s, self.cumulative, self.route[:, 1])])


def _mover(route: np.ndarray, stop_along_m: float, **fields) -> _Mover:
    step = np.hypot(*np.diff(route, axis=0).T)
    cumulative = np.concatenate([[0.0], np.cumsum(step)])
    # The first leg runs straight from the arm's end towards the centre.
    return _Mover(route, cumulative, ARM_LENGTH_M - stop_along_m, **fields)


def signal_green(arm: str, time_s: float) -> bool:
    """Whether ``arm``'s vehicles have green at ``time_s`` (pedestrians: ``"pedestrians"``)."""
    cycle = len(ARMS) * (GREEN_S + CLEARANCE_S) + PEDESTRIAN_S + CLEARANCE_S
    phase = time_s % cycle
    if arm == "pedestrians":
        start = len(ARMS) * (GREEN_S + CLEARANCE_S)
        return start <= phase < start + PEDESTRIAN_S
    start = list(ARMS).index(arm) * (GREEN_S + CLEARANCE_S)
    return start <= phase < start + GREEN_S


def _simulate(movers: list[_Mover], end_s: float) -> list[list[tuple[float, float]]]:
    """Step every mover on the 0.1 s grid; each one's positions from its arrival on."""
    tracks: list[list[tuple[float, float]]] = [[] for _ in movers]
    pedestrian = np.array([one.kind == "pedestrian" for one in movers])
    bicycle = np.array([one.kind == "bicycle" for one in movers])
    length = np.array([one.length for one in movers])
    for step in range(int(end_s / STEP_S) + 1):
        time_s = step * STEP_S
        active = np.array([one.arrive <= time_s + 1e-9 and not one.done for one in movers],
                          bool)
        index = np.flatnonzero(active)
        if len(index) == 0:
            continue
        here = np.array([movers[i].position() for i in index])
        ahead = np.array([movers[i].position(movers[i].s + 1.0) for i in index]) - here
        heading = ahead / np.maximum(np.hypot(ahead[:, 0], ahead[:, 1]), 1e-9)[:, None]
        speed = np.array([max(movers[i].speed, 0.0) for i in index])
        # Gap to whoever is ahead in the same lane (vehicles and bicycles apart).
        offset = here[None, :, :] - here[:, None, :]  # [i, j]: from i to j
        along = np.einsum("ijk,ik->ij", offset, heading)
        lateral = np.abs(offset[..., 0] * heading[:, None, 1]
                         - offset[..., 1] * heading[:, None, 0])
        same_lane = ((bicycle[index][:, None] == bicycle[index][None, :])
                     & ~pedestrian[index][None, :] & (along > 0) & (lateral <= 1.2))
        gap = np.maximum(along - (length[index][:, None] + length[index][None, :]) / 2 - 2.0,
                         0.0)
        follow = np.where(same_lane, np.minimum(np.sqrt(2 * _BRAKING * gap),
                                                speed[None, :] + gap / 1.5), np.inf)
        follow_limit = follow.min(axis=1)
        for row, i in enumerate(index.tolist()):
            one = movers[i]
            if one.speed < 0:
                one.speed = one.desired
            limit = one.desired
            if one.kind != "pedestrian":
                limit = min(limit, float(follow_limit[row]))
            # Stop at the line unless green (or too close to stop when it turned).
            to_line = one.stop_s - one.length / 2 - one.s
            if to_line > -0.5 and not one.committed:
                signal = "pedestrians" if one.kind == "pedestrian" else one.arm
                if signal_green(signal, time_s):
                    one.committed = to_line < 1.0
                elif (one.speed**2 / (3 * _BRAKING) < to_line or to_line < 0.5
                      or one.kind == "pedestrian"):
                    # Stops (the comfortable curve keeps it well inside hard braking).
                    limit = min(limit, math.sqrt(2 * _BRAKING * max(to_line, 0.0)))
                else:
                    one.committed = True  # too close to stop even braking hard: goes on
            one.speed = max(0.0, min(one.speed + one.acceleration * STEP_S, limit))
            one.s += one.speed * STEP_S
            if one.s >= one.cumulative[-1]:
                one.done = True
            tracks[i].append(tuple(one.position().tolist()))
    return tracks


def crossroads_world(
    seed: int = 0, duration_s: float = 120.0, fps: float | None = None,
    vehicles_per_minute: float = 16.0, pedestrians: int = 16,
) -> WorldSpec:
    """Mixed traffic through a signalised crossroads, seeded arrivals, classes and routes.

    Args:
        seed: seed of every random choice.
        duration_s: how long vehicles and pedestrians keep arriving; the scene lasts until
            the last of them has left.
        fps: frame rate (default 10).
        vehicles_per_minute: mean arrivals over all four arms.
        pedestrians: how many pedestrians cross.
    """
    rng = np.random.default_rng(seed)
    names = list(ARMS)
    movers: list[_Mover] = []
    classes: list[str] = []
    od: list[tuple[str, str] | None] = []
    arrive_until = duration_s
    time_s = 0.0
    while True:
        time_s += float(rng.exponential(60.0 / vehicles_per_minute))
        if time_s > arrive_until:
            break
        origin = names[int(rng.integers(4))]
        class_name = str(rng.choice([name for name, _ in _CLASS_SHARE],
                                    p=[share for _, share in _CLASS_SHARE]))
        if class_name == "bicycle":
            turn = int(rng.choice([2, 3], p=[0.7, 0.3]))  # straight on or right
            offset = BICYCLE_OFFSET_M
        else:
            turn = int(rng.choice([1, 2, 3], p=[0.25, 0.5, 0.25]))  # left, straight, right
            offset = LANE_OFFSET_M
        destination = names[(names.index(origin) + turn) % 4]
        size = class_size(class_name, rng)
        low, high = _DESIRED_SPEED[class_name]
        movers.append(_mover(
            _route(origin, destination, offset), STOP_LINE_M, length=size[0],
            desired=float(rng.uniform(low, high)), acceleration=_ACCELERATION[class_name],
            arrive=round(time_s / STEP_S) * STEP_S, arm=origin,
            kind="bicycle" if class_name == "bicycle" else "vehicle",
        ))
        classes.append(class_name)
        od.append((origin, destination))
    sizes = [class_size(name, rng) for name in classes]
    for _ in range(pedestrians):
        # Along a pavement to the kerb of the crossing ahead, across, and on along the
        # pavement of the next arm.
        arm = names[int(rng.integers(4))]
        side = 1.0 if rng.random() < 0.5 else -1.0
        lateral = float(rng.uniform(-0.6, 0.6))
        angle = ARMS[arm]
        start = _point(angle, ARM_LENGTH_M - 5.0, side * (PAVEMENT_OFFSET_M + lateral))
        kerb = _point(angle, JUNCTION_M + 1.0, side * (PAVEMENT_OFFSET_M + lateral))
        across = _point(angle, JUNCTION_M + 1.0, -side * (PAVEMENT_OFFSET_M + lateral))
        away = _point(angle, ARM_LENGTH_M - 5.0, -side * (PAVEMENT_OFFSET_M + lateral))
        route = np.vstack([start, kerb, across, away])
        mover = _mover(route, 0.0, length=0.4, desired=float(rng.uniform(1.1, 1.6)),
                       acceleration=1.0,
                       arrive=round(float(rng.uniform(0.0, arrive_until)) / STEP_S) * STEP_S,
                       arm=arm, kind="pedestrian")
        mover.stop_s = float(mover.cumulative[1]) + mover.length / 2
        movers.append(mover)
        classes.append("person")
        sizes.append(class_size("person", rng))
        od.append(None)
    tracks = _simulate(movers, duration_s + 120.0)
    objects = []
    for index, (mover, class_name, size, xy) in enumerate(
            zip(movers, classes, sizes, tracks, strict=True)):
        if len(xy) < 2:
            continue
        path = SampledPath(mover.arrive, STEP_S, tuple(xy))
        objects.append(MovingObject(index + 1, class_name, size, path))
    cameras = tuple(
        Camera.from_pose(name, (x, y, 10.0), math.degrees(math.atan2(-y, -x)), 24.0, 760.0,
                         _IMAGE_SIZE)
        for name, x, y in (("NE", 19.0, 19.0), ("NW", -19.0, 19.0), ("SW", -19.0, -19.0),
                           ("SE", 19.0, -19.0))
    )
    return WorldSpec(
        name="crossroads",
        cameras=cameras,
        objects=tuple(objects),
        area=(-40.0, -40.0, 40.0, 40.0),
        duration_s=max(mover.arrive + len(xy) * STEP_S for mover, xy in zip(
            movers, tracks, strict=True)) + 1.0,
        fps=10.0 if fps is None else fps,
    )


def crossroads_od(world: WorldSpec) -> Counter[tuple[str, str]]:
    """The true (origin arm, destination arm) of every vehicle (bicycles too) of the world."""
    od: Counter[tuple[str, str]] = Counter()
    for item in world.objects:
        if item.class_name == "person":
            continue
        path = item.path
        assert isinstance(path, SampledPath)
        od[(_arm_of(np.asarray(path.xy[0])), _arm_of(np.asarray(path.xy[-1])))] += 1
    return od


def _arm_of(point: np.ndarray) -> str:
    angle = math.degrees(math.atan2(point[1], point[0])) % 360.0
    return min(ARMS, key=lambda name: abs((angle - ARMS[name] + 180.0) % 360.0 - 180.0))


def make_crossroads_scene(seed: int = 0, duration_s: float = 120.0) -> Scene:
    """The :class:`Scene` of :func:`crossroads_world`."""
    return SyntheticWorld(crossroads_world(seed, duration_s)).scene()
