"""Oriented 3-D boxes standing on the ground, and their exact image boxes in a camera.

Objects of the synthetic world are such boxes (length along the heading, width across, height
up). Projection of boxes partly behind a camera: the box (a convex polyhedron) is clipped in
3-D against the camera's near plane (:data:`NEAR_PLANE_M` in front of the camera centre) before
projecting, so the 2-D box is the exact bounding box of the visible part of the solid; a box
entirely behind the near plane is invisible.
"""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.detections import CLASS_SIZE_PRIORS

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

NEAR_PLANE_M = 0.1


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
    (NaN where nothing is in front of the camera, or where the box reaches past the lens's
    field, :attr:`Camera.field_radius`) and (N,) bool.
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
    if math.isfinite(camera.field_radius) and keep.any():
        # Past its field a polynomial lens model folds back and would image the box on
        # pixels that show nearer ground (Camera.field_radius): a box reaching beyond the
        # field is not seen, as one whose image misses the sensor.
        outside = np.zeros(keep.shape, dtype=bool)
        outside[keep] = ~camera.in_field(points[keep])
        in_front &= ~outside.any(axis=1)
        pixels[outside.any(axis=1)] = np.nan
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
