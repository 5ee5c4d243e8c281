"""Paths the objects of the synthetic world move along: loops, lanes, waypoints, random walks,
simulated samples.

Each path gives, for an array of times, the ground position, the heading and whether the object
is present (:class:`PathSample`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

@dataclass(frozen=True)
class PathSample:
    """Positions of one object at given times.

    Attributes:
        xy: (T, 2) footprint centre in metres (NaN where absent).
        heading_deg: (T,) direction of travel, degrees counter-clockwise from +x.
        present: (T,) bool, True while the object is in the world.
    """

    xy: FloatArray
    heading_deg: FloatArray
    present: BoolArray


@dataclass(frozen=True)
class LoopPath:
    """Constant speed around a circle (a roundabout lane).

    Attributes:
        centre: (x, y) of the circle, metres.
        radius: metres.
        speed: metres per second along the circle.
        start_angle_deg: where the object is at ``start_s``, degrees from +x.
        clockwise: direction (False = counter-clockwise, right-hand traffic).
        start_s: time the object appears, seconds.
        laps: number of laps before it disappears; None keeps it going.
    """

    centre: tuple[float, float]
    radius: float
    speed: float
    start_angle_deg: float = 0.0
    clockwise: bool = False
    start_s: float = 0.0
    laps: float | None = None

    def sample(self, times: FloatArray) -> PathSample:
        """Position, heading and presence at each of ``times`` (seconds)."""
        elapsed = np.asarray(times, dtype=np.float64) - self.start_s
        travelled = self.speed * elapsed
        present = elapsed >= 0
        if self.laps is not None:
            present &= travelled <= self.laps * 2 * np.pi * self.radius + 1e-9
        sign = -1.0 if self.clockwise else 1.0
        angle = np.radians(self.start_angle_deg) + sign * travelled / self.radius
        xy = np.column_stack(
            [
                self.centre[0] + self.radius * np.cos(angle),
                self.centre[1] + self.radius * np.sin(angle),
            ]
        )
        heading = np.degrees(angle + sign * np.pi / 2)
        return _masked(xy, heading, present)


@dataclass(frozen=True)
class WaypointPath:
    """Constant speed along a polyline; the object exists from the first to the last point.

    Attributes:
        points: ((x, y), ...) at least two waypoints, metres.
        speed: metres per second.
        start_s: time the object is at the first waypoint, seconds.
    """

    points: tuple[tuple[float, float], ...]
    speed: float
    start_s: float = 0.0

    def __post_init__(self) -> None:
        if len(self.points) < 2:
            raise ValueError("a waypoint path needs at least two points")
        if self.speed <= 0:
            raise ValueError(f"speed must be positive, got {self.speed}")

    def sample(self, times: FloatArray) -> PathSample:
        """Position, heading and presence at each of ``times`` (seconds)."""
        points = np.asarray(self.points, dtype=np.float64)
        segments = np.diff(points, axis=0)
        lengths = np.hypot(segments[:, 0], segments[:, 1])
        cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
        travelled = self.speed * (np.asarray(times, dtype=np.float64) - self.start_s)
        present = (travelled >= 0) & (travelled <= cumulative[-1])
        distance = np.clip(travelled, 0.0, cumulative[-1])
        xy = np.column_stack(
            [
                np.interp(distance, cumulative, points[:, 0]),
                np.interp(distance, cumulative, points[:, 1]),
            ]
        )
        index = np.clip(
            np.searchsorted(cumulative, distance, side="right") - 1, 0, len(segments) - 1
        )
        heading = np.degrees(np.arctan2(segments[index, 1], segments[index, 0]))
        return _masked(xy, heading, present)


def LanePath(
    start: tuple[float, float], end: tuple[float, float], speed: float, start_s: float = 0.0
) -> WaypointPath:
    """A straight lane from ``start`` to ``end`` (metres) at ``speed`` m/s from ``start_s``."""
    return WaypointPath((tuple(start), tuple(end)), speed, start_s)  # type: ignore[arg-type]


@dataclass(frozen=True)
class RandomWalkPath:
    """A smooth random walk (a pedestrian wandering) kept inside a rectangle.

    The heading diffuses (``turn_deg_per_sqrt_s`` standard deviation per square root of a
    second) and is pulled back towards the area centre near the border. The walk is
    integrated on a fixed 0.1 s grid from its own seed, so it does not depend on the frame
    rate it is sampled at.

    Attributes:
        start: (x, y) position at ``start_s``, metres.
        area: (x_min, y_min, x_max, y_max) the walker stays in, metres.
        speed: walking speed, metres per second.
        seed: seed of this walk.
        turn_deg_per_sqrt_s: heading diffusion.
        start_s, end_s: when the walker appears and disappears (None: never).
        start_heading_deg: initial heading; None draws one from the seed.
    """

    start: tuple[float, float]
    area: tuple[float, float, float, float]
    speed: float = 1.3
    seed: int = 0
    turn_deg_per_sqrt_s: float = 20.0
    start_s: float = 0.0
    end_s: float | None = None
    start_heading_deg: float | None = None

    _STEP_S = 0.1

    def sample(self, times: FloatArray) -> PathSample:
        """Position, heading and presence at each of ``times`` (seconds)."""
        times = np.asarray(times, dtype=np.float64)
        present = times >= self.start_s
        if self.end_s is not None:
            present &= times <= self.end_s
        horizon = float(times.max() - self.start_s) if len(times) else 0.0
        steps = max(int(np.ceil(max(horizon, 0.0) / self._STEP_S)) + 2, 2)
        rng = np.random.default_rng(self.seed)
        heading = (
            rng.uniform(-np.pi, np.pi)
            if self.start_heading_deg is None
            else np.radians(self.start_heading_deg)
        )
        noise = rng.standard_normal(steps) * np.radians(self.turn_deg_per_sqrt_s)
        noise *= np.sqrt(self._STEP_S)
        x_min, y_min, x_max, y_max = self.area
        centre = np.array([(x_min + x_max) / 2, (y_min + y_max) / 2])
        margin = 0.15 * min(x_max - x_min, y_max - y_min)
        position = np.array(self.start, dtype=np.float64)
        track = np.empty((steps, 2))
        headings = np.empty(steps)
        for step in range(steps):
            track[step], headings[step] = position, heading
            outside = max(
                x_min + margin - position[0],
                position[0] - (x_max - margin),
                y_min + margin - position[1],
                position[1] - (y_max - margin),
                0.0,
            )
            if outside > 0:
                # Turn towards the centre, harder the further into the margin.
                to_centre = np.arctan2(*(centre - position)[::-1])
                error = np.angle(np.exp(1j * (to_centre - heading)))
                heading += min(1.0, outside / margin) * 0.5 * error
            heading += noise[step]
            position = position + self.speed * self._STEP_S * np.array(
                [np.cos(heading), np.sin(heading)]
            )
            position = np.clip(position, [x_min, y_min], [x_max, y_max])
        grid = self.start_s + self._STEP_S * np.arange(steps)
        clamped = np.clip(times, grid[0], grid[-1])
        xy = np.column_stack(
            [np.interp(clamped, grid, track[:, 0]), np.interp(clamped, grid, track[:, 1])]
        )
        unwrapped = np.unwrap(headings)
        heading_deg = np.degrees(np.interp(clamped, grid, unwrapped))
        return _masked(xy, heading_deg, present)


def _masked(xy: FloatArray, heading_deg: FloatArray, present: BoolArray) -> PathSample:
    xy = xy.copy()
    heading_deg = np.asarray(heading_deg, dtype=np.float64).copy()
    xy[~present] = np.nan
    heading_deg[~present] = np.nan
    return PathSample(xy=xy, heading_deg=heading_deg, present=present)




@dataclass(frozen=True, eq=False)
class SampledPath:
    """Positions simulated on a fixed time grid (a car in a queue, a pedestrian waiting).

    Between grid points the position is interpolated linearly; the heading is that of the
    motion, kept through stops. The object is present from the first to the last sample.

    Attributes:
        start_s: time of the first sample, seconds.
        step_s: time between samples, seconds.
        xy: ((x, y), ...) positions on the grid, metres (at least two).
    """

    start_s: float
    step_s: float
    xy: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        if len(self.xy) < 2 or self.step_s <= 0:
            raise ValueError("a sampled path needs two samples and a positive step")

    def sample(self, times: FloatArray) -> PathSample:
        """Position, heading and presence at each of ``times`` (seconds)."""
        times = np.asarray(times, dtype=np.float64)
        points = np.asarray(self.xy, dtype=np.float64)
        grid = self.start_s + self.step_s * np.arange(len(points))
        present = (times >= grid[0] - 1e-9) & (times <= grid[-1] + 1e-9)
        xy = np.column_stack([np.interp(times, grid, points[:, 0]),
                              np.interp(times, grid, points[:, 1])])
        step = np.diff(points, axis=0)
        moving = np.hypot(step[:, 0], step[:, 1]) > 1e-6
        heading = np.degrees(np.arctan2(step[:, 1], step[:, 0]))
        # Hold the last heading of motion through stops (the first motion before it).
        index = np.where(moving, np.arange(len(step)), -1)
        index = np.maximum.accumulate(index)
        first = int(np.argmax(moving)) if moving.any() else 0
        heading = heading[np.where(index >= 0, index, first)]
        segment = np.clip(np.searchsorted(grid, times, side="right") - 1, 0, len(step) - 1)
        return _masked(xy, heading[segment], present)


Path = LoopPath | WaypointPath | RandomWalkPath | SampledPath
"""Any of the paths: an object with ``sample(times) -> PathSample``."""
