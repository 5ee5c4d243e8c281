"""A synthetic world: cameras over a ground plane, 3D boxes moving along paths.

This is cblrs' stand-in for the paper's Carla data sets. Objects are oriented 3D boxes
standing on the ground (length along the heading, width across, height up); each camera's
detection boxes are the image-space bounding boxes of the projected 3D boxes, and the ground
truth is the centre of each footprint. Everything is exact and deterministic for a seed, so
it can check localisation, targeting and tracking without any data set.

Projection of boxes partly behind a camera: the box (a convex polyhedron) is clipped in 3D
against the camera's near plane (:data:`NEAR_PLANE_M` in front of the camera centre) before
projecting, so the 2D box is the exact bounding box of the visible part of the solid;
a box entirely behind the near plane is invisible.

What a camera reports (:meth:`SyntheticWorld.camera_boxes`): a box is kept when at least
``min_visible_fraction`` of its unclipped image box lies inside the image and it is at least
``min_box_height_px`` tall; with ``occlusion`` it is dropped when more than
``max_occluded_fraction`` of it is covered by the image boxes of nearer objects (depth of
the box centre along the optical axis; a box-level approximation) or when that fraction of
15 points on its surface is hidden behind a :class:`Structure` (exact ray test). Ground
truth keeps every object in view of some camera, occluded or not, on the ground plane.

Build a world with :class:`WorldSpec` (cameras from :meth:`Camera.from_pose`, objects with
:class:`LoopPath`, :func:`LanePath`, :class:`WaypointPath` or :class:`RandomWalkPath`), or
take a preset with :func:`make_scene` (``roundabout``, ``plaza``).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.datasets.scene import Scene
from cblrs.detections import Detections, Tracks, class_id_of
from cblrs.errors import DatasetError
from cblrs.plane import PlaneSpec

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

NEAR_PLANE_M = 0.1
"""Camera depth (metres) in front of which boxes are clipped before projection."""

# Corner signs (along the length, across the width, up); the edge list below indexes them.
_CORNER_SIGNS = np.array(
    [
        [1, 1, 0],
        [1, -1, 0],
        [-1, -1, 0],
        [-1, 1, 0],
        [1, 1, 1],
        [1, -1, 1],
        [-1, -1, 1],
        [-1, 1, 1],
    ],
    dtype=np.float64,
)
_FACES = ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
_EDGES = np.array(
    [
        [0, 1],
        [1, 2],
        [2, 3],
        [3, 0],
        [4, 5],
        [5, 6],
        [6, 7],
        [7, 4],
        [0, 4],
        [1, 5],
        [2, 6],
        [3, 7],
    ]
)


def box_corners_3d(
    centre_xy: NDArray,
    size_lwh: NDArray,
    yaw_deg: NDArray | float,
    base_z: NDArray | float = 0.0,
) -> FloatArray:
    """The eight corners of oriented boxes standing on a horizontal plane.

    Args:
        centre_xy: (N, 2) footprint centres, metres.
        size_lwh: (N, 3) or (3,) length (along the heading), width, height in metres.
        yaw_deg: heading, degrees counter-clockwise from world +x, scalar or (N,).
        base_z: height of the box bottom, metres, scalar or (N,).

    Returns:
        (N, 8, 3) corners in world metres; corners 0-3 are the bottom face, 4-7 the top.
    """
    centre_xy = np.asarray(centre_xy, dtype=np.float64)
    if centre_xy.ndim != 2 or centre_xy.shape[1] != 2:
        raise ValueError(f"centre_xy must have shape (N, 2), got {centre_xy.shape}")
    count = len(centre_xy)
    size_lwh = np.broadcast_to(np.asarray(size_lwh, dtype=np.float64), (count, 3))
    yaw = np.radians(np.broadcast_to(np.asarray(yaw_deg, dtype=np.float64), (count,)))
    base = np.broadcast_to(np.asarray(base_z, dtype=np.float64), (count,))
    heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)  # (N, 2)
    across = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    half_length = size_lwh[:, 0:1, None] / 2.0  # (N, 1, 1)
    half_width = size_lwh[:, 1:2, None] / 2.0
    along = _CORNER_SIGNS[None, :, 0:1] * half_length * heading[:, None, :]  # (N, 8, 2)
    side = _CORNER_SIGNS[None, :, 1:2] * half_width * across[:, None, :]
    corners = np.empty((count, 8, 3))
    corners[:, :, :2] = centre_xy[:, None, :] + along + side
    corners[:, :, 2] = base[:, None] + _CORNER_SIGNS[None, :, 2] * size_lwh[:, 2:3]
    return corners


def _clipped_vertices(camera: Camera, corners: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Vertices of each box clipped to the near half-space, in world metres.

    Returns:
        ``(points, keep)``: (N, 20, 3) candidate points (8 corners then 12 edge crossings)
        and (N, 20) bool, True for points of the clipped polyhedron.
    """
    rotation, translation = camera._pose()
    depth = corners @ rotation[2] + translation[2]  # (N, 8) camera z
    in_front = depth >= NEAR_PLANE_M
    start, end = _EDGES[:, 0], _EDGES[:, 1]
    depth_start, depth_end = depth[:, start], depth[:, end]  # (N, 12)
    crosses = in_front[:, start] != in_front[:, end]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(crosses, (NEAR_PLANE_M - depth_start) / (depth_end - depth_start), 0)
    crossing = corners[:, start] + fraction[..., None] * (corners[:, end] - corners[:, start])
    points = np.concatenate([corners, crossing], axis=1)
    keep = np.concatenate([in_front, crosses], axis=1)
    return points, keep


def project_boxes_3d_unclipped(
    camera: Camera,
    centre_xy: NDArray,
    size_lwh: NDArray,
    yaw_deg: NDArray | float,
    base_z: NDArray | float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """Image bounding boxes of 3D boxes, not clipped to the image.

    Same arguments as :func:`project_boxes_3d`. Returns ``(xyxy, in_front)``: (N, 4) pixels
    (NaN where nothing is in front of the camera) and (N,) bool.
    """
    corners = box_corners_3d(centre_xy, size_lwh, yaw_deg, base_z)
    count = len(corners)
    xyxy = np.full((count, 4), np.nan)
    if count == 0:
        return xyxy, np.zeros(0, dtype=bool)
    points, keep = _clipped_vertices(camera, corners)
    pixels = np.full((count, points.shape[1], 2), np.nan)
    if keep.any():
        # Points exactly on the near plane can fall a hair short of it after rounding;
        # project them all and rely on `keep` rather than on project_points' own test.
        rotation, translation = camera._pose()
        flat = points[keep]
        camera_xyz = flat @ rotation.T + translation
        camera_xyz[:, 2] = np.maximum(camera_xyz[:, 2], NEAR_PLANE_M)
        world = (camera_xyz - translation) @ rotation
        projected, _ = camera.project_points(world)
        pixels[keep] = projected
    in_front: BoolArray = np.asarray(keep.any(axis=1), dtype=bool)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        # Rows with nothing in front are all-NaN; they are excluded by `in_front` anyway.
        warnings.simplefilter("ignore", category=RuntimeWarning)
        xyxy[in_front, 0:2] = np.nanmin(pixels[in_front], axis=1)
        xyxy[in_front, 2:4] = np.nanmax(pixels[in_front], axis=1)
    return xyxy, in_front


def clip_boxes(xyxy: NDArray, image_size: tuple[int, int]) -> tuple[FloatArray, BoolArray]:
    """Clip pixel boxes to an image.

    Args:
        xyxy: (N, 4) pixels, NaN rows allowed.
        image_size: (width, height) in pixels.

    Returns:
        ``(clipped, nonempty)``: (N, 4) boxes within ``[-0.5, width - 0.5] x
        [-0.5, height - 0.5]`` (the image's pixel area) and (N,) bool, False where the clipped
        box has no area (or the row was NaN).
    """
    xyxy = np.asarray(xyxy, dtype=np.float64)
    width, height = image_size
    clipped = xyxy.copy()
    clipped[:, [0, 2]] = np.clip(clipped[:, [0, 2]], -0.5, width - 0.5)
    clipped[:, [1, 3]] = np.clip(clipped[:, [1, 3]], -0.5, height - 0.5)
    with np.errstate(invalid="ignore"):
        nonempty = (clipped[:, 2] > clipped[:, 0]) & (clipped[:, 3] > clipped[:, 1])
    return clipped, nonempty


def project_boxes_3d(
    camera: Camera,
    centre_xy: NDArray,
    size_lwh: NDArray,
    yaw_deg: NDArray | float,
    base_z: NDArray | float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """Image boxes of N oriented 3D boxes, clipped to the image.

    Each box is clipped against the camera's near plane in 3D (see the module docstring),
    its vertices projected with :meth:`Camera.project_points` (lens distortion included),
    and the 2D bounding box of the projections clipped to the image.

    Args:
        camera: a posed camera.
        centre_xy: (N, 2) footprint centres in world metres.
        size_lwh: (N, 3) or (3,) length along the heading, width, height in metres.
        yaw_deg: (N,) or scalar heading, degrees counter-clockwise from world +x.
        base_z: (N,) or scalar height of the box bottom in metres.

    Returns:
        ``(xyxy, visible)``: (N, 4) float64 pixels and (N,) bool. ``visible`` is False when
        the whole box is behind the near plane or its box misses the image; such rows are NaN.
    """
    xyxy, in_front = project_boxes_3d_unclipped(camera, centre_xy, size_lwh, yaw_deg, base_z)
    clipped, nonempty = clip_boxes(xyxy, camera.image_size)
    visible = in_front & nonempty
    clipped[~visible] = np.nan
    return clipped, visible


def project_box_3d(
    camera: Camera,
    centre_xy: NDArray | tuple[float, float],
    size_lwh: NDArray | tuple[float, float, float],
    yaw_deg: float,
    base_z: float = 0.0,
) -> tuple[FloatArray, bool]:
    """Image box of one oriented 3D box standing on the ground, clipped to the image.

    Args:
        camera: a posed camera.
        centre_xy: (2,) footprint centre in metres.
        size_lwh: (3,) length (along the heading), width, height in metres.
        yaw_deg: heading in degrees counter-clockwise from world +x.
        base_z: height of the box bottom in metres.

    Returns:
        ``(xyxy, visible)``: (4,) pixels (x_min, y_min, x_max, y_max), NaN when invisible,
        and whether any part of the box is seen.

    Example:
        >>> camera = Camera.from_pose("top", (0, 0, 10), 0, 90, 500, (640, 480))
        >>> xyxy, visible = project_box_3d(camera, (0, 0), (2, 2, 0.0), 0)
        >>> visible, xyxy.round(1).tolist()
        (True, [269.5, 189.5, 369.5, 289.5])
    """
    xyxy, visible = project_boxes_3d(
        camera,
        np.asarray(centre_xy, dtype=np.float64).reshape(1, 2),
        np.asarray(size_lwh, dtype=np.float64).reshape(1, 3),
        float(yaw_deg),
        float(base_z),
    )
    return xyxy[0], bool(visible[0])


# ---------------------------------------------------------------------------- objects and paths

CLASS_SIZE_PRIORS: dict[str, tuple[float, float, float]] = {
    "person": (0.5, 0.5, 1.75),
    "car": (4.5, 1.8, 1.5),
    "bicycle": (1.8, 0.6, 1.7),
    "motorcycle": (2.1, 0.8, 1.5),
    "bus": (12.0, 2.55, 3.2),
    "truck": (8.0, 2.5, 3.5),
}
"""Typical (length, width, height) in metres of each class in :data:`CLASS_NAMES`."""


def class_size(
    class_name: str, rng: np.random.Generator | None = None, variation: float = 0.06
) -> tuple[float, float, float]:
    """Size prior of a class, optionally varied by a relative normal spread (clipped at 2 sigma).

    Args:
        class_name: one of :data:`CLASS_SIZE_PRIORS`.
        rng: random generator; None returns the prior itself.
        variation: relative standard deviation of each dimension.

    Returns:
        (length, width, height) in metres.
    """
    if class_name not in CLASS_SIZE_PRIORS:
        raise ValueError(
            f"no size prior for class {class_name!r}; known: {', '.join(CLASS_SIZE_PRIORS)}"
        )
    prior = np.asarray(CLASS_SIZE_PRIORS[class_name])
    if rng is None:
        return tuple(float(v) for v in prior)  # type: ignore[return-value]
    factor = 1.0 + variation * np.clip(rng.standard_normal(3), -2.0, 2.0)
    return tuple(float(v) for v in prior * factor)  # type: ignore[return-value]


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


Path = LoopPath | WaypointPath | RandomWalkPath


@dataclass(frozen=True)
class MovingObject:
    """One object of the world.

    Attributes:
        object_id: ground-truth identity (unique in the world).
        class_name: one of :data:`CLASS_NAMES`.
        size_lwh: (length, width, height) in metres.
        path: where it is over time (any object with ``sample(times) -> PathSample``).
    """

    object_id: int
    class_name: str
    size_lwh: tuple[float, float, float]
    path: Path

    def __post_init__(self) -> None:
        class_id_of(self.class_name)
        if len(self.size_lwh) != 3 or min(self.size_lwh) <= 0:
            raise ValueError(f"size_lwh must be three positive metres, got {self.size_lwh}")


@dataclass(frozen=True)
class Structure:
    """A static 3D box standing on the ground (a building, a monument, a kiosk).

    Structures hide objects behind them but are never detected and have no ground truth.

    Attributes:
        centre: (x, y) footprint centre, metres.
        size_lwh: (length, width, height) in metres.
        yaw_deg: orientation of the length axis, degrees from +x.
        name: a label.
    """

    centre: tuple[float, float]
    size_lwh: tuple[float, float, float]
    yaw_deg: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        if len(self.size_lwh) != 3 or min(self.size_lwh) <= 0:
            raise ValueError(f"size_lwh must be three positive metres, got {self.size_lwh}")

    def corners(self) -> FloatArray:
        """(8, 3) corners in world metres (see :func:`box_corners_3d`)."""
        return box_corners_3d(
            np.array([self.centre], float), np.asarray(self.size_lwh, float), self.yaw_deg
        )[0]

    def blocks(self, origin: NDArray, points: NDArray) -> BoolArray:
        """Whether the segments from ``origin`` (3,) to ``points`` (M, 3) pass through it."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        yaw = np.radians(self.yaw_deg)
        # Into the structure's frame: x along its length, y across, z up from its base.
        rotation = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
        start = np.asarray(origin, dtype=np.float64).copy()
        start[:2] = rotation @ (start[:2] - self.centre)
        ends = points.copy()
        ends[:, :2] = (points[:, :2] - self.centre) @ rotation.T
        direction = ends - start
        half = np.array(self.size_lwh) / 2.0
        low = np.array([-half[0], -half[1], 0.0])
        high = np.array([half[0], half[1], self.size_lwh[2]])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_low = (low - start) / direction
            t_high = (high - start) / direction
        t_near = np.nanmax(np.where(direction != 0, np.minimum(t_low, t_high), -np.inf), axis=1)
        t_far = np.nanmin(np.where(direction != 0, np.maximum(t_low, t_high), np.inf), axis=1)
        # Axes the segment runs parallel to: it must lie within that slab.
        parallel_outside = ((direction == 0) & ((start < low) | (start > high))).any(axis=1)
        # The end point itself (on the object) does not count: stop just short of it.
        return (t_near < t_far) & (t_far > 0) & (t_near < 1 - 1e-6) & ~parallel_outside


@dataclass(frozen=True)
class GroundMarking:
    """A filled polygon painted on the ground (roads, islands); used for pictures only.

    Attributes:
        polygon: ((x, y), ...) vertices in metres, at least three.
        colour: (r, g, b) 0..255.
    """

    polygon: tuple[tuple[float, float], ...]
    colour: tuple[int, int, int]


@dataclass(frozen=True)
class WorldSpec:
    """Everything that defines a synthetic scene.

    Attributes:
        name: scene name.
        cameras: posed cameras (see :meth:`Camera.from_pose`).
        objects: the moving objects.
        area: (x_min, y_min, x_max, y_max) of the ground plane, metres.
        duration_s: length of the sequence, seconds.
        fps: frame rate; frame k is captured at k / fps seconds.
        bits: bits per channel of the ground plane's colour code.
        min_visible_fraction: a camera reports a box only if at least this fraction of its
            (unclipped) image box lies inside the image.
        min_box_height_px: smaller boxes are not detected.
        occlusion: drop boxes mostly hidden behind nearer boxes in the same camera, or
            behind structures.
        max_occluded_fraction: a box more covered than this is dropped when ``occlusion``.
        structures: static boxes that hide objects (never detected).
        markings: ground paint for pictures (drawn in the order given); no effect on data.
    """

    name: str
    cameras: tuple[Camera, ...]
    objects: tuple[MovingObject, ...]
    area: tuple[float, float, float, float]
    duration_s: float = 10.0
    fps: float = 10.0
    bits: int = 16
    min_visible_fraction: float = 0.5
    min_box_height_px: float = 8.0
    occlusion: bool = True
    max_occluded_fraction: float = 0.75
    structures: tuple[Structure, ...] = ()
    markings: tuple[GroundMarking, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "structures", tuple(self.structures))
        object.__setattr__(self, "markings", tuple(self.markings))
        if not self.cameras:
            raise DatasetError("a synthetic world needs at least one camera.")
        for camera in self.cameras:
            if not camera.has_pose:
                raise DatasetError(f"camera {camera.name!r} needs a pose to project 3D boxes.")
        ids = [item.object_id for item in self.objects]
        if len(set(ids)) != len(ids):
            raise DatasetError("object ids of a synthetic world must be unique.")
        if self.duration_s <= 0 or self.fps <= 0:
            raise DatasetError(
                "duration and frame rate must be positive, "
                f"got {self.duration_s} s at {self.fps} fps."
            )
        x_min, y_min, x_max, y_max = self.area
        if not (x_max > x_min and y_max > y_min):
            raise DatasetError(f"area must be (x_min, y_min, x_max, y_max), got {self.area}.")


@dataclass(frozen=True)
class ObjectStates:
    """All objects over all frames.

    Attributes:
        times: (T,) seconds.
        xy: (T, N, 2) footprint centres in metres (NaN where absent).
        yaw_deg: (T, N) headings in degrees.
        present: (T, N) bool.
    """

    times: FloatArray
    xy: FloatArray
    yaw_deg: FloatArray
    present: BoolArray


class SyntheticWorld:
    """Generates a :class:`Scene` from a :class:`WorldSpec`.

    Example:
        >>> camera = Camera.from_pose("top", (0, 0, 20), 0, 90, 800, (640, 480))
        >>> walker = MovingObject(1, "person", (0.5, 0.5, 1.75), LanePath((-4, 0), (4, 0), 1.0))
        >>> spec = WorldSpec("tiny", (camera,), (walker,), area=(-5, -5, 5, 5), duration_s=2)
        >>> scene = SyntheticWorld(spec).scene()
        >>> len(scene.frames), len(scene.detections[0][0])
        (20, 1)
    """

    def __init__(self, spec: WorldSpec):
        self.spec = spec

    @property
    def times(self) -> FloatArray:
        count = max(int(np.floor(self.spec.duration_s * self.spec.fps + 1e-9)), 1)
        return np.arange(count) / self.spec.fps

    def states(self) -> ObjectStates:
        times = self.times
        count = len(self.spec.objects)
        xy = np.full((len(times), count, 2), np.nan)
        yaw = np.full((len(times), count), np.nan)
        present = np.zeros((len(times), count), dtype=bool)
        for column, item in enumerate(self.spec.objects):
            sample = item.path.sample(times)
            xy[:, column], yaw[:, column], present[:, column] = (
                sample.xy,
                sample.heading_deg,
                sample.present,
            )
        return ObjectStates(times=times, xy=xy, yaw_deg=yaw, present=present)

    def plane(self) -> PlaneSpec:
        x_min, y_min, x_max, y_max = self.spec.area
        return PlaneSpec(
            1, (x_min, y_min), x_max - x_min, y_max - y_min, bits=self.spec.bits, name="ground"
        )

    def camera_boxes(
        self, states: ObjectStates, camera: Camera
    ) -> tuple[FloatArray, BoolArray, BoolArray]:
        """Boxes of every object at every frame in one camera.

        Returns:
            ``(xyxy, detected, in_view)``: (T, N, 4) clipped pixel boxes, (T, N) bool for the
            boxes the camera reports (visible enough, large enough, not occluded) and
            (T, N) bool for objects in view regardless of occlusion.
        """
        spec = self.spec
        frames, count = states.present.shape
        sizes = np.array([item.size_lwh for item in spec.objects], dtype=np.float64).reshape(
            count, 3
        )
        flat_present = states.present.reshape(-1)
        flat_xy = np.nan_to_num(states.xy.reshape(-1, 2))
        flat_yaw = np.nan_to_num(states.yaw_deg.reshape(-1))
        flat_sizes = np.broadcast_to(sizes[None], (frames, count, 3)).reshape(-1, 3)
        unclipped, in_front = project_boxes_3d_unclipped(camera, flat_xy, flat_sizes, flat_yaw)
        clipped, nonempty = clip_boxes(unclipped, camera.image_size)
        in_front &= flat_present & nonempty
        with np.errstate(invalid="ignore"):
            full_area = _area(unclipped)
            inside = np.where(in_front, _area(clipped) / np.maximum(full_area, 1e-12), 0.0)
            tall = (clipped[:, 3] - clipped[:, 1]) >= spec.min_box_height_px
        in_view = in_front & (inside >= spec.min_visible_fraction) & tall
        clipped[~in_front] = np.nan
        xyxy = clipped.reshape(frames, count, 4)
        in_view = in_view.reshape(frames, count)
        detected = in_view.copy()
        if spec.occlusion and spec.structures and count:
            hidden = self._hidden_by_structures(camera, states, sizes, in_view)
            detected &= ~hidden
        if spec.occlusion and count > 1:
            depth = _camera_depth(camera, states.xy, sizes)
            occluders = in_front.reshape(frames, count)
            for frame in range(frames):
                hidden = occluded(
                    xyxy[frame], depth[frame], occluders[frame], spec.max_occluded_fraction
                )
                detected[frame] &= ~hidden
        return xyxy, detected, in_view

    def _hidden_by_structures(
        self, camera: Camera, states: ObjectStates, sizes: FloatArray, candidates: BoolArray
    ) -> BoolArray:
        """(T, N) bool: objects whose sample points are mostly hidden behind structures."""
        hidden = np.zeros(candidates.shape, dtype=bool)
        frame_index, column = np.nonzero(candidates)
        if len(frame_index) == 0:
            return hidden
        corners = box_corners_3d(
            states.xy[frame_index, column], sizes[column], states.yaw_deg[frame_index, column]
        )
        # Corners, face centres and the centre of each box: 15 points that see or are seen.
        faces = np.stack([corners[:, list(face)].mean(axis=1) for face in _FACES], axis=1)
        points = np.concatenate([corners, faces, corners.mean(axis=1, keepdims=True)], axis=1)
        blocked = np.zeros(points.shape[:2], dtype=bool)
        for structure in self.spec.structures:
            blocked |= structure.blocks(camera.centre, points.reshape(-1, 3)).reshape(blocked.shape)
        hidden[frame_index, column] = blocked.mean(axis=1) > self.spec.max_occluded_fraction
        return hidden

    def boxes_at(self, states: ObjectStates, frame_index: int) -> tuple[FloatArray, NDArray]:
        """Corners and ids of the objects present at one frame.

        Returns:
            ``(corners, object_ids)``: (N, 8, 3) world metres and (N,) int64.
        """
        present = states.present[frame_index]
        sizes = np.array([item.size_lwh for item in self.spec.objects], dtype=np.float64)
        ids = np.array([item.object_id for item in self.spec.objects], dtype=np.int64)
        if not present.any():
            return np.zeros((0, 8, 3)), np.zeros(0, dtype=np.int64)
        corners = box_corners_3d(
            states.xy[frame_index][present],
            sizes.reshape(-1, 3)[present],
            states.yaw_deg[frame_index][present],
        )
        return corners, ids[present]

    def scene(self, name: str | None = None) -> Scene:
        """Project every object into every camera and collect the :class:`Scene`.

        Ground truth holds the footprint centre of each object at the frames where at least
        one camera has it in view (occluded or not) and it stands on the ground plane, i.e.
        the objects inside the observed area, as in annotated data sets.
        """
        spec = self.spec
        states = self.states()
        frames, count = states.present.shape
        class_ids = np.array([class_id_of(item.class_name) for item in spec.objects], np.int64)
        object_ids = np.array([item.object_id for item in spec.objects], np.int64)
        per_camera = [self.camera_boxes(states, camera) for camera in spec.cameras]
        detections: list[list[Detections]] = []
        for frame in range(frames):
            row = []
            for xyxy, detected, _ in per_camera:
                keep = detected[frame]
                row.append(
                    Detections(
                        xyxy=xyxy[frame][keep],
                        confidence=np.ones(int(keep.sum())),
                        class_id=class_ids[keep],
                        object_id=object_ids[keep],
                    )
                )
            detections.append(row)
        seen = np.zeros((frames, count), dtype=bool)
        for _, _, in_view in per_camera:
            seen |= in_view
        # Positions off the ground plane have no colour, so no camera could report them.
        plane = self.plane()
        seen &= plane.contains(np.nan_to_num(states.xy, nan=np.inf).reshape(-1, 2)).reshape(
            frames, count
        )
        frame_index, column = np.nonzero(seen)
        ground_truth = Tracks(
            frame=frame_index.astype(np.int64),
            timestamp=states.times[frame_index],
            track_id=object_ids[column],
            world_xy=states.xy[frame_index, column],
            class_id=class_ids[column],
        )
        logger.debug(
            "synthetic scene %s: %d frames, %d cameras, %d objects, %d detections",
            spec.name,
            frames,
            len(spec.cameras),
            count,
            sum(len(d) for row in detections for d in row),
        )
        return Scene(
            name=name or spec.name,
            cameras=list(spec.cameras),
            frames=np.arange(frames, dtype=np.int64),
            timestamps=states.times,
            detections=detections,
            ground_truth=ground_truth,
            plane=self.plane(),
        )


def _area(xyxy: FloatArray) -> FloatArray:
    return np.maximum(xyxy[..., 2] - xyxy[..., 0], 0.0) * np.maximum(
        xyxy[..., 3] - xyxy[..., 1], 0.0
    )


def _camera_depth(camera: Camera, xy: FloatArray, sizes: FloatArray) -> FloatArray:
    """Camera depth (metres) of each box centre, (T, N); NaN where absent."""
    rotation, translation = camera._pose()
    centres = np.concatenate(
        [xy, np.broadcast_to(sizes[None, :, 2:3] / 2.0, (*xy.shape[:2], 1))], axis=-1
    )
    return centres @ rotation[2] + translation[2]


def occluded(
    xyxy: NDArray, depth: NDArray, occluders: NDArray, max_fraction: float, samples: int = 12
) -> BoolArray:
    """Which boxes are mostly covered by nearer boxes of the same image.

    The coverage of each box is measured on a ``samples x samples`` grid of points inside it
    by the union of the boxes with smaller depth.

    Args:
        xyxy: (N, 4) pixel boxes (NaN rows are ignored).
        depth: (N,) distance from the camera, metres.
        occluders: (N,) bool, which boxes can hide others (e.g. all boxes in front).
        max_fraction: a box whose covered fraction exceeds this is occluded.
        samples: grid points per side.

    Returns:
        (N,) bool, True for occluded boxes.
    """
    xyxy = np.asarray(xyxy, dtype=np.float64)
    count = len(xyxy)
    hidden = np.zeros(count, dtype=bool)
    valid = occluders & np.isfinite(xyxy).all(axis=1) & np.isfinite(depth)
    rows = np.flatnonzero(valid)
    if len(rows) < 2:
        return hidden
    fractions = (np.arange(samples) + 0.5) / samples
    for row in rows:
        nearer = rows[depth[rows] < depth[row]]
        if len(nearer) == 0:
            continue
        x0, y0, x1, y1 = xyxy[row]
        grid_x = x0 + fractions * (x1 - x0)
        grid_y = y0 + fractions * (y1 - y0)
        boxes = xyxy[nearer]
        covers_x = (grid_x[None, :] >= boxes[:, 0:1]) & (grid_x[None, :] <= boxes[:, 2:3])
        covers_y = (grid_y[None, :] >= boxes[:, 1:2]) & (grid_y[None, :] <= boxes[:, 3:4])
        covered = (covers_y[:, :, None] & covers_x[:, None, :]).any(axis=0)
        hidden[row] = covered.mean() > max_fraction
    return hidden


# ---------------------------------------------------------------------------- presets

_IMAGE_SIZE = (1280, 720)


def roundabout_world(
    seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """Two cameras over a roundabout; one car drives a full circle (the paper's hand-over case).

    The cameras stand on masts west and east of the roundabout and look across it; the
    monument on the central island (a 10 x 10 x 7 m block set diagonally) hides the
    far side of the ring from each. The car (radius 12 m, 7.5 m/s, counter-clockwise)
    starts and ends where only camera A sees it; on the way it passes an overlap (north or
    south, seen by both), the stretch only camera B sees, and a second overlap, so its
    identity has to be handed from A to B and back. One lap takes about 10 s; the default
    duration (10.6 s) covers it.
    """
    rng = np.random.default_rng(seed)
    radius, speed = 12.0, 7.5
    # A small seeded jitter of the mounting so that seeds differ without moving the overlaps.
    jitter = rng.uniform(-0.3, 0.3, size=4)
    cameras = (
        Camera.from_pose(
            "A", (-24.0, -2.0 + jitter[0], 9.0), 4.8 + jitter[1], 22.0, 900.0, _IMAGE_SIZE
        ),
        Camera.from_pose(
            "B", (24.0, 2.0 + jitter[2], 9.0), 184.8 + jitter[3], 22.0, 900.0, _IMAGE_SIZE
        ),
    )
    car = MovingObject(
        1, "car", class_size("car", rng), LoopPath((0.0, 0.0), radius, speed, start_angle_deg=160.0)
    )
    monument = (Structure((0.0, 0.0), (10.0, 10.0, 7.0), 45.0, "monument"),)
    return WorldSpec(
        name="roundabout",
        cameras=cameras,
        objects=(car,),
        area=(-20.0, -20.0, 20.0, 20.0),
        duration_s=10.6 if duration_s is None else duration_s,
        fps=10.0 if fps is None else fps,
        structures=monument,
        markings=roundabout_markings(radius),
    )


def roundabout_markings(radius: float) -> tuple[GroundMarking, ...]:
    """Asphalt ring, kerbs and a green central island of a roundabout (for pictures only)."""
    angles = np.linspace(0, 2 * np.pi, 97)[:-1]

    def circle(r: float) -> tuple[tuple[float, float], ...]:
        return tuple((float(r * np.cos(a)), float(r * np.sin(a))) for a in angles)

    return (
        GroundMarking(circle(radius + 2.2), (70, 72, 76)),
        GroundMarking(circle(radius - 2.0), (215, 215, 210)),
        GroundMarking(circle(radius - 2.4), (92, 140, 70)),
    )


def plaza_world(
    seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """Four corner cameras over a 30 x 20 m plaza with a road along its south side.

    Twenty people wander (random walks that cross each other), six more walk straight across
    at staggered times (arrivals and departures), and two cars drive along the road,
    hiding people behind them for a while.
    """
    rng = np.random.default_rng(seed)
    duration = 30.0 if duration_s is None else duration_s
    cameras = tuple(
        Camera.from_pose(name, (x, y, 8.0), pan, 32.0, 820.0, _IMAGE_SIZE)
        for name, x, y, pan in (
            ("NW", -17.0, 12.0, -35.0),
            ("NE", 17.0, 12.0, -145.0),
            ("SE", 17.0, -15.0, 140.0),
            ("SW", -17.0, -15.0, 40.0),
        )
    )
    walk_area = (-13.0, -8.0, 13.0, 9.0)
    objects: list[MovingObject] = []
    for index in range(20):
        start = (
            rng.uniform(walk_area[0] + 2, walk_area[2] - 2),
            rng.uniform(walk_area[1] + 2, walk_area[3] - 2),
        )
        path = RandomWalkPath(
            start=start,
            area=walk_area,
            speed=float(rng.uniform(0.9, 1.6)),
            seed=int(rng.integers(2**31)),
        )
        objects.append(MovingObject(index + 1, "person", class_size("person", rng), path))
    crossings = [
        ((-15.0, -6.0), (15.0, 8.0)),
        ((15.0, 4.0), (-15.0, -3.0)),
        ((-6.0, 10.0), (4.0, -9.0)),
        ((8.0, -9.0), (-3.0, 10.0)),
        ((-15.0, 1.0), (15.0, 0.0)),
        ((15.0, -7.0), (-15.0, 6.0)),
    ]
    for index, (start, end) in enumerate(crossings):
        lane: Path = LanePath(
            start, end, float(rng.uniform(1.1, 1.6)), start_s=float(index * duration / 7)
        )
        objects.append(MovingObject(21 + index, "person", class_size("person", rng), lane))
    roads = [
        ((-40.0, -11.0), (40.0, -11.0), 0.1 * duration),
        ((40.0, -13.0), (-40.0, -13.0), 0.4 * duration),
    ]
    for index, (start, end, start_s) in enumerate(roads):
        road: Path = LanePath(start, end, float(rng.uniform(5.0, 7.0)), start_s=float(start_s))
        objects.append(MovingObject(101 + index, "car", class_size("car", rng), road))
    return WorldSpec(
        name="plaza",
        cameras=cameras,
        objects=tuple(objects),
        area=(-20.0, -16.0, 20.0, 14.0),
        duration_s=duration,
        fps=5.0 if fps is None else fps,
    )


PRESETS = {"roundabout": roundabout_world, "plaza": plaza_world}
"""Named synthetic worlds: name -> ``function(seed, duration_s, fps) -> WorldSpec``."""


def make_world(
    preset: str, seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """The :class:`WorldSpec` of a preset (see :data:`PRESETS`); None keeps its defaults."""
    try:
        builder = PRESETS[preset]
    except KeyError:
        raise DatasetError(
            f"unknown synthetic preset {preset!r}; known presets: {', '.join(sorted(PRESETS))}."
        ) from None
    return builder(seed=seed, duration_s=duration_s, fps=fps)


def make_scene(
    preset: str, seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> Scene:
    """A synthetic :class:`Scene` from a preset, deterministic for a seed.

    Args:
        preset: ``"roundabout"`` or ``"plaza"``.
        seed: seed of every random choice (sizes, walks, start times).
        duration_s: sequence length in seconds; None uses the preset's default.
        fps: frame rate; None uses the preset's default.

    Example:
        >>> scene = make_scene("roundabout")
        >>> scene.camera_names, round(scene.frame_interval, 3)
        (['A', 'B'], 0.1)
    """
    return SyntheticWorld(make_world(preset, seed, duration_s, fps)).scene()
