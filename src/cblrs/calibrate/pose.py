"""A camera pose from a ground homography and a known or estimated focal length."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cblrs.camera import Camera

FloatArray = NDArray[np.float64]

# A focal length outside [0.1, 20] x the image's larger side is no real lens: the fit is
# degenerate (nearly fronto-parallel view, points bunched together).
FOCAL_RANGE = (0.1, 20.0)


@dataclass(frozen=True, eq=False)
class RecoveredPose:
    """A camera pose recovered from a ground homography (see :func:`pose_from_homography`).

    Attributes:
        camera: the posed camera (K, R, t) closest to the homography.
        focal_px: its focal length, pixels.
        focal_estimated: True when the focal length came from the homography itself.
        orthogonality: how far the homography is from a rotation (0 = exactly one).
    """

    camera: Camera
    focal_px: float
    focal_estimated: bool
    orthogonality: float


def estimate_focal(homography: ArrayLike, image_size: tuple[int, int]) -> float | None:
    """The focal length (pixels) that makes a ground homography a rotation, or None.

    With square pixels and the principal point at the image centre, ``K^-1 H = [r1 r2 t]``
    up to scale needs ``r1 . r2 = 0`` and ``|r1| = |r2|``: two equations in ``1 / f^2``
    (Zhang's constraints for a single view), solved in the least-squares sense. A camera
    looking straight down (no perspective) leaves ``f`` undetermined: None.
    """
    width, height = image_size
    shift = np.array([[1, 0, -(width - 1) / 2.0], [0, 1, -(height - 1) / 2.0], [0, 0, 1]])
    matrix = shift @ np.asarray(homography, dtype=np.float64)
    matrix = matrix / np.abs(matrix).max()
    (h11, h12, _), (h21, h22, _), (h31, h32, _) = matrix
    # Each constraint reads a * w + b = 0 with w = 1 / f^2; rows are scaled by a typical f^2
    # so that both weigh alike.
    typical = float(max(width, height)) ** 2
    a = np.array([h11 * h12 + h21 * h22, h11**2 + h21**2 - h12**2 - h22**2]) / typical
    b = np.array([h31 * h32, h31**2 - h32**2])
    denominator = float(a @ a)
    if denominator == 0:
        return None
    inverse_square = -float(a @ b) / denominator * (1.0 / typical)
    if not (np.isfinite(inverse_square) and inverse_square > 0):
        return None
    focal = 1.0 / math.sqrt(inverse_square)
    low, high = (bound * max(width, height) for bound in FOCAL_RANGE)
    # A tiny |b| (camera looking nearly straight down) makes f arbitrary: check that the
    # constraints really select it (the residual at f must be well below that at f / 2, 2 f).
    residual = _orthogonality(matrix, focal)
    if not (low <= focal <= high) or residual > 0.5 * min(
        _orthogonality(matrix, focal / 2), _orthogonality(matrix, focal * 2)
    ):
        return None
    return focal


def _orthogonality(centred_homography: FloatArray, focal: float) -> float:
    """How far ``diag(1/f, 1/f, 1) H`` is from two orthonormal columns (0 = exactly)."""
    matrix = np.diag([1.0 / focal, 1.0 / focal, 1.0]) @ centred_homography
    first, second = matrix[:, 0], matrix[:, 1]
    norm1, norm2 = float(np.linalg.norm(first)), float(np.linalg.norm(second))
    cosine = float(first @ second) / (norm1 * norm2)
    return math.hypot(cosine, (norm1 - norm2) / (norm1 + norm2))


def pose_from_homography(
    homography: ArrayLike,
    image_size: tuple[int, int],
    focal_px: float | None = None,
    name: str = "camera",
) -> tuple[RecoveredPose | None, str]:
    """Recover K, R, t from a ground homography and a known or estimated focal length.

    ``K^-1 H = lambda [r1 r2 t]``: the scale comes from ``|r1| = |r2| = 1``, its sign from the
    seen ground lying in front of the camera (the homography's sign, see
    :meth:`Camera.from_homography`), ``r3 = r1 x r2`` and the nearest rotation (SVD). That
    resolves the usual two-fold ambiguity with the camera above the plane; a camera that
    comes out below it means left-handed world axes and is refused.

    Args:
        homography: (3, 3) world metres -> undistorted pixels.
        image_size: (width, height) pixels; the principal point is its centre.
        focal_px: the focal length in pixels, or None to estimate it (:func:`estimate_focal`).
        name: name of the returned camera.

    Returns:
        ``(pose, "")`` or ``(None, reason)`` with a short reason when no pose can be had.
    """
    width, height = image_size
    camera = Camera.from_homography(name, np.asarray(homography, dtype=np.float64), image_size)
    estimated = focal_px is None
    focal = estimate_focal(camera.homography, image_size) if focal_px is None else float(focal_px)
    if focal is None:
        return (
            None,
            "the focal length cannot be read from a homography without perspective; give focal_px",
        )
    intrinsics = np.array(
        [[focal, 0, (width - 1) / 2.0], [0, focal, (height - 1) / 2.0], [0, 0, 1]]
    )
    matrix = np.linalg.solve(intrinsics, camera.homography)
    norms = np.linalg.norm(matrix[:, :2], axis=0)
    scale = 2.0 / float(norms.sum())
    first, second, translation = (scale * matrix[:, index] for index in range(3))
    approximate = np.column_stack([first, second, np.cross(first, second)])
    left, _, right = np.linalg.svd(approximate)
    rotation = left @ right
    if np.linalg.det(rotation) < 0:
        return None, "the homography is not the view of a plane by a camera"
    posed = Camera.from_extrinsics(name, intrinsics, rotation, translation, image_size)
    if not posed.centre[2] > 0:
        return None, "the camera would be below the ground: the world axes look left-handed"
    orthogonality = _orthogonality(
        np.array([[1, 0, -(width - 1) / 2.0], [0, 1, -(height - 1) / 2.0], [0, 0, 1]])
        @ camera.homography,
        focal,
    )
    return RecoveredPose(posed, focal, estimated, orthogonality), ""
