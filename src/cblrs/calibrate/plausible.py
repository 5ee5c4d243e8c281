"""Fits that are mathematically fine but physically absurd: refused, naming the likely mistake.

A homography fits ground positions in centimetres as well as in metres, and swapped columns
(``v,u`` for ``u,v``, or ``y,x`` for ``x,y``) only mirror the ground; the errors in pixels stay
small, so the fit alone looks good. What gives them away is the camera they imply:

- a clicked pixel outside the image (``u`` and ``v`` swapped on a frame that is not square);
- a mirror image of the ground: seen from above, the clicked points go round the other way in
  the image than on the plan, which no camera above a right-handed world can see (``u, v`` or
  ``x, y`` swapped; a world whose axes really are left-handed is allowed on request);
- a camera hundreds of metres high, or points that span kilometres (ground positions in
  centimetres, millimetres or map pixels read as metres).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.points import Correspondences
from cblrs.errors import CalibrationError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A camera higher than this (metres) is refused unless the caller raises the limit.
MAX_HEIGHT_M = 100.0
#: Points spanning more than this (metres) with no camera position to judge are refused.
MAX_SPREAD_M = 2000.0
#: How far outside the image (share of its size) a clicked pixel may lie: box bottoms of
#: people cut by the border, and click noise, land a few pixels out.
_OUTSIDE_SHARE = 0.02


def check_in_image(points: Correspondences, image_size: tuple[int, int]) -> None:
    """Refuse clicked pixels outside the image, saying when ``u, v`` look swapped."""
    width, height = image_size
    margin = _OUTSIDE_SHARE * np.array([width, height], dtype=np.float64)
    limit = np.array([width, height], dtype=np.float64)

    def outside(image_xy: FloatArray) -> BoolArray:
        return np.any((image_xy < -margin) | (image_xy > limit + margin), axis=1)

    out = np.flatnonzero(outside(points.image_xy))
    if not len(out):
        return
    index = int(out[0])
    u, v = points.image_xy[index]
    swapped = not outside(points.image_xy[:, ::-1]).any()
    hint = (
        "u and v look swapped (every point fits the image with the columns exchanged): the "
        "columns are u (pixels from the left), then v (pixels from the top)"
        if swapped
        else "check the image size and that u is pixels from the left, v from the top"
    )
    raise CalibrationError(
        f"{points.source}: {points.names[index]} (u, v = {u:g}, {v:g}) lies outside the "
        f"{width}x{height} image ({len(out)} of {len(points)} points do); {hint}."
    )


def check_handedness(
    points: Correspondences, homography: FloatArray, inliers: BoolArray, left_handed: bool
) -> None:
    """Refuse points that show the ground mirrored, unless the world is said to be left-handed.

    Args:
        points: the clicked points.
        homography: (3, 3) world -> image homography fitted to them.
        inliers: (N,) the points the homography agrees with.
        left_handed: the world's axes are left-handed on purpose (seen from above, x turns
            clockwise onto y): a mirrored fit is then what is expected.
    """
    world = np.column_stack([points.world_xy[inliers], np.ones(int(inliers.sum()))])
    depth = world @ homography[2]
    # The Jacobian of the homography at a point has the sign of det(H) / w^3: negative for a
    # camera above a right-handed world (the image's v grows downwards), positive mirrored.
    orientation = np.sign(np.linalg.det(homography)) * np.sign(depth)
    mirrored = bool(np.all(orientation > 0))
    if mirrored and not left_handed:
        raise CalibrationError(
            f"{points.source}: the points show the ground mirrored (a camera seeing them would "
            "stand below the ground): are u and v, or x and y, swapped, or are x, y map pixels "
            "(y growing down the map: use --world map)? If the world's axes "
            "really are left-handed (seen from above, x turns clockwise onto y), say so "
            "(--left-handed; in a site file left_handed: true)."
        )


def check_scale(
    points: Correspondences,
    height_m: float | None,
    max_height_m: float = MAX_HEIGHT_M,
) -> None:
    """Refuse a camera higher than ``max_height_m``, or, with no height, points spanning more
    than :data:`MAX_SPREAD_M`: ground positions in the wrong unit, named."""
    spread = _spread(points.world_xy)
    if height_m is not None:
        if height_m <= max_height_m:
            return
        what = f"the fit puts the camera {height_m:,.1f} m high"
        scaled = height_m
    else:
        if spread <= MAX_SPREAD_M:
            return
        what = f"the points span {spread:,.0f} m"
        scaled = spread / 10.0  # a typical view spans about ten times the camera's height
    guess = "are x and y in another unit than metres, or map pixels (use --world map)?"
    for unit, factor in (("centimetres", 100.0), ("millimetres", 1000.0)):
        if 1.0 <= scaled / factor <= 30.0:
            as_metres = (
                f"divided by {factor:g} the camera is {height_m / factor:.2f} m high"
                if height_m is not None
                else f"divided by {factor:g} they span {spread / factor:,.1f} m"
            )
            guess = (
                f"are x and y in {unit}? They must be metres ({as_metres}), or map pixels "
                "with --world map."
            )
            break
    raise CalibrationError(
        f"{points.source}: {what}: {guess} A camera really higher than {max_height_m:g} m: "
        "raise --max-height-m (in a site file max_height_m)."
    )


def _spread(world_xy: FloatArray) -> float:
    """The diagonal of the points' bounding box, metres."""
    lower, upper = world_xy.min(axis=0), world_xy.max(axis=0)
    return float(math.hypot(*(upper - lower)))
