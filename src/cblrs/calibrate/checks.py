"""Points that cannot calibrate a camera: refused before any fit, with one sentence."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.points import Correspondences
from cblrs.calibrate.refine import normalising
from cblrs.errors import CalibrationError

FloatArray = NDArray[np.float64]


def image_size_of(image_size: tuple[int, int], source: str) -> tuple[int, int]:
    """``image_size`` as positive integers (width, height); CalibrationError naming ``source``
    otherwise."""
    try:
        width, height = (int(value) for value in image_size)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"{source}: the image size must be (width, height) pixels."
        ) from None
    if width <= 0 or height <= 0:
        raise CalibrationError(f"{source}: the image size must be positive, got {width}x{height}.")
    return width, height


def check_spread(points: Correspondences) -> None:
    """Refuse points that cannot determine a homography: all on one line, or 3 of 4 on one."""
    for array, where in ((points.world_xy, "world"), (points.image_xy, "image")):
        centred = array - array.mean(axis=0)
        singular = np.linalg.svd(centred, compute_uv=False)
        if singular[0] == 0 or singular[1] < 1e-3 * singular[0]:
            raise CalibrationError(
                f"{points.source}: the {len(array)} {where} points lie on one line; a ground "
                "homography needs at least 4 points that are not all on one line."
            )
    # Beyond one line: a homography's 8 unknowns need a well-conditioned linear system
    # (e.g. 4 points with 3 on one line, or many on one line and one off it, do not).
    matrix = dlt_matrix(points.image_xy, points.world_xy)
    singular = np.linalg.svd(matrix, compute_uv=False)
    if singular[7] < 1e-5 * singular[0]:
        raise CalibrationError(
            f"{points.source}: the points do not pin down a homography (three of four, or all but "
            "one, lie on one line); click points spread over the ground, not along one edge."
        )


def dlt_matrix(image_xy: FloatArray, world_xy: FloatArray) -> FloatArray:
    """Hartley-normalised DLT system of the homography world -> image, (2N, 9)."""
    image_norm, world_norm = normalising(image_xy), normalising(world_xy)
    image = np.column_stack([image_xy, np.ones(len(image_xy))]) @ image_norm.T
    world = np.column_stack([world_xy, np.ones(len(world_xy))]) @ world_norm.T
    rows = []
    for (x, y, w), (u, v, s) in zip(world, image, strict=True):
        rows.append([0, 0, 0, -s * x, -s * y, -s * w, v * x, v * y, v * w])
        rows.append([s * x, s * y, s * w, 0, 0, 0, -u * x, -u * y, -u * w])
    return np.array(rows, dtype=np.float64)
