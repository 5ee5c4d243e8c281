"""A synthetic world: cameras over a ground plane, 3D boxes moving along paths.

This is cblrs' stand-in for the paper's Carla data sets. Objects are oriented 3D boxes
standing on the ground (length along the heading, width across, height up); each camera's
detection boxes are the image-space bounding boxes of the projected 3D boxes, and the ground
truth is the centre of each footprint. Everything is exact and deterministic for a seed, so
it can check localisation, targeting and tracking without any data set.

The boxes' geometry (clipping at the near plane, projection) is in
:mod:`cblrs.datasets.boxes3d`, the paths objects follow in :mod:`cblrs.datasets.paths` (their
names are importable from here too), the two preset worlds in :mod:`cblrs.datasets.presets`.

What a camera reports (:meth:`SyntheticWorld.camera_boxes`): a box is kept when at least
``min_visible_fraction`` of its unclipped image box lies inside the image and it is at least
``min_box_height_px`` tall; with ``occlusion`` it is dropped when more than
``max_occluded_fraction`` of it is covered by the image boxes of nearer objects (depth of
the box centre along the optical axis; a box-level approximation) or when that fraction of
15 points on its surface is hidden behind a :class:`Structure` (exact ray test). Ground
truth keeps every object in view of some camera, occluded or not, on the ground plane.

Build a world with :class:`WorldSpec` (cameras from :meth:`Camera.from_pose`, objects with
:class:`LoopPath`, :func:`LanePath`, :class:`WaypointPath` or :class:`RandomWalkPath`), or
take a preset with :func:`cblrs.datasets.presets.make_scene` (``roundabout``, ``plaza``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.datasets.boxes3d import (
    _FACES,
    CLASS_SIZE_PRIORS,
    NEAR_PLANE_M,
    box_corners_3d,
    class_size,
    clip_boxes,
    project_box_3d,
    project_boxes_3d,
    project_boxes_3d_unclipped,
)
from cblrs.datasets.paths import (
    LanePath,
    LoopPath,
    Path,
    PathSample,
    RandomWalkPath,
    WaypointPath,
)
from cblrs.datasets.scene import Scene
from cblrs.detections import Detections, Tracks, class_id_of
from cblrs.errors import DatasetError
from cblrs.plane import PlaneSpec

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "CLASS_SIZE_PRIORS",
    "NEAR_PLANE_M",
    "GroundMarking",
    "LanePath",
    "LoopPath",
    "MovingObject",
    "ObjectStates",
    "Path",
    "PathSample",
    "RandomWalkPath",
    "Structure",
    "SyntheticWorld",
    "WaypointPath",
    "WorldSpec",
    "box_corners_3d",
    "class_size",
    "clip_boxes",
    "occluded",
    "project_box_3d",
    "project_boxes_3d",
    "project_boxes_3d_unclipped",
]


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
        # Only objects present at a frame are projected (in a long world most are absent).
        present_rows = np.flatnonzero(flat_present)
        unclipped = np.full((len(flat_present), 4), np.nan)
        in_front = np.zeros(len(flat_present), dtype=bool)
        if len(present_rows):
            unclipped[present_rows], in_front[present_rows] = project_boxes_3d_unclipped(
                camera, flat_xy[present_rows], flat_sizes[present_rows], flat_yaw[present_rows]
            )
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
    boxes = xyxy[rows]
    # Every box against every other at once: (R, S) sample coordinates inside each box,
    # (R, S, R) whether box o covers them, only where o is nearer than the box itself.
    grid_x = boxes[:, 0:1] + fractions[None, :] * (boxes[:, 2:3] - boxes[:, 0:1])
    grid_y = boxes[:, 1:2] + fractions[None, :] * (boxes[:, 3:4] - boxes[:, 1:2])
    nearer = depth[rows][None, :] < depth[rows][:, None]
    covers_x = (grid_x[:, :, None] >= boxes[None, None, :, 0]) & (
        grid_x[:, :, None] <= boxes[None, None, :, 2]) & nearer[:, None, :]
    covers_y = (grid_y[:, :, None] >= boxes[None, None, :, 1]) & (
        grid_y[:, :, None] <= boxes[None, None, :, 3])
    covered = (covers_y[:, :, None, :] & covers_x[:, None, :, :]).any(axis=3)
    hidden[rows] = covered.reshape(len(rows), -1).mean(axis=1) > max_fraction
    return hidden
