"""Pure geometry the camera model is built on: rotations and ground-plane homographies.

* :func:`rotation_from_vector` and :func:`rotation_from_pose` build world-to-camera rotations
  (from a Rodrigues vector, OpenCV's arithmetic without OpenCV; from pan, tilt and roll).
* :func:`plane_homography` is the map ``K [r1 r2 (z r3 + t)]`` from a horizontal plane to
  pixels, and :func:`homography_pixel_to_world` inverts such a map for undistorted pixels.

Conventions (metres, OpenCV pixels, ``X_cam = R @ X_world + t``) are those of
:mod:`cblrs.camera`, whose :class:`~cblrs.camera.Camera` uses every function here.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# Rays meeting a plane farther away than this (metres) count as missing it: they graze the
# horizon, where rounding decides the side and the hit point is meaningless. The limit is a
# world distance, so it does not depend on how a bare homography happens to be scaled.
MAX_WORLD_DISTANCE_M = 1e7
_DOUBLE_EPSILON = float(np.finfo(np.float64).eps)  # OpenCV's DBL_EPSILON


def rotation_from_vector(vector: NDArray) -> FloatArray:
    """The (3, 3) rotation of a Rodrigues vector (axis times angle, radians).

    OpenCV's ``cv2.Rodrigues`` arithmetic step by step (the angle from the sum of squares,
    the axis scaled by its inverse, ``cos I + (1 - cos) r r^T + sin [r]x``), so the matrices
    are bit for bit OpenCV's (tested), without importing OpenCV.
    """
    x, y, z = (float(value) for value in np.asarray(vector, np.float64).ravel())
    theta = math.sqrt(x * x + y * y + z * z)
    if theta < _DOUBLE_EPSILON:
        return np.eye(3)
    cosine, sine = math.cos(theta), math.sin(theta)
    inverse = 1.0 / theta
    x, y, z = x * inverse, y * inverse, z * inverse
    outer = np.array([[x * x, x * y, x * z], [x * y, y * y, y * z], [x * z, y * z, z * z]])
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return cosine * np.eye(3) + (1.0 - cosine) * outer + sine * cross


def _as_points(points: NDArray[np.floating] | list, name: str) -> FloatArray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {array.shape}")
    return array


def rotation_from_pose(pan_deg: float, tilt_deg: float, roll_deg: float = 0.0) -> FloatArray:
    """World-to-camera rotation for a camera given by pan, tilt and roll.

    Args:
        pan_deg: heading of the optical axis in the ground plane, degrees counter-clockwise
            from the world +x axis.
        tilt_deg: angle of the optical axis below the horizon, degrees (90 looks straight
            down).
        roll_deg: rotation about the optical axis, degrees (clockwise in the image).

    Returns:
        (3, 3) rotation matrix R with ``X_cam = R @ (X_world - C)``.
    """
    pan, tilt, roll = np.radians([pan_deg, tilt_deg, roll_deg])
    forward = np.array([np.cos(tilt) * np.cos(pan), np.cos(tilt) * np.sin(pan), -np.sin(tilt)])
    # The image x axis stays horizontal for zero roll, even when looking straight down.
    right = np.array([np.sin(pan), -np.cos(pan), 0.0])
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    cos_r, sin_r = np.cos(roll), np.sin(roll)
    roll_matrix = np.array([[cos_r, -sin_r, 0.0], [sin_r, cos_r, 0.0], [0.0, 0.0, 1.0]])
    return roll_matrix @ rotation


def plane_homography(
    intrinsics: NDArray, rotation: NDArray, translation: NDArray, height_m: float
) -> FloatArray:
    """Homography from the plane z = height_m (metres) to pixels: ``K [r1 r2 (z r3 + t)]``."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64).ravel()
    columns = np.column_stack(
        [rotation[:, 0], rotation[:, 1], height_m * rotation[:, 2] + translation]
    )
    return np.asarray(intrinsics, dtype=np.float64) @ columns


def homography_pixel_to_world(homography: NDArray, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
    """Map undistorted pixels through the inverse of a world-to-pixel homography.

    The homography's sign must make points in front of the camera have a positive third
    coordinate (true for ``K [r1 r2 t]`` and for :meth:`Camera.from_homography`).

    Args:
        homography: (3, 3) world (metres) -> undistorted pixel map.
        pixels: (N, 2) undistorted pixel coordinates.

    Returns:
        ``(world_xy, valid)``: (N, 2) metres and (N,) bool. Rows whose ray does not meet the
        plane in front of the camera (at or above the horizon, or beyond
        :data:`MAX_WORLD_DISTANCE_M`) are invalid and NaN.
    """
    pixels = _as_points(pixels, "pixels")
    inverse = np.linalg.inv(np.asarray(homography, dtype=np.float64))
    homogeneous = np.column_stack([pixels, np.ones(len(pixels))]) @ inverse.T
    scale = homogeneous[:, 2]
    # The depth of the world point is proportional to 1 / scale (exactly 1 / scale for
    # K [r1 r2 t]), so the point is in front of the camera exactly when scale > 0.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        world_xy = homogeneous[:, :2] / scale[:, None]
        valid = (scale > 0) & (np.abs(world_xy) <= MAX_WORLD_DISTANCE_M).all(axis=1)
    world_xy[~valid] = np.nan
    return world_xy, valid
