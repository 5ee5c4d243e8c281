"""Left-handed calibrations: on which side of a camera its ground lies, and the equivalent
proper-rotation description when it lies behind.

Some published extrinsics (every MultiviewX camera: its world comes from Unity) describe a
world whose (x, y, up) axes are left-handed as seen by the camera: ``K [R | t] X`` still gives
the right pixel as a homogeneous point, but every ground point has *negative* depth, so any
code that rejects points behind the camera sees nothing. ``K [R | t] X`` and ``-K [R | t] X``
are the same pixel; ``-R`` is an improper rotation, but with the height axis mirrored,
``R' = -R diag(1, 1, -1)`` is a proper rotation and ``t' = -t``:
``R' (x, y, -z) + t' = -(R (x, y, z) + t)``. :func:`orient_to_ground` detects such a camera
(the ground it sees lies behind it) and returns this equivalent description: it reprojects
every point identically, has positive depths, keeps ground x, y, and records
``height_axis = -1`` so that heights stay heights (metres above the ground) in every
:class:`~cblrs.camera.Camera` method. :func:`ground_depth_sign` tells the side; the calibration
readers (:mod:`cblrs.calibration`) pass every camera they read through :func:`orient_to_ground`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cblrs.camera import Camera


def ground_depth_sign(
    camera: Camera, area: tuple[float, float, float, float] | None = None
) -> int:
    """On which side of ``camera`` the ground it sees lies: +1 in front, -1 behind.

    A homography maps a ground point to a pixel up to a scale of either sign; the sign of
    that scale is the sign of the point's depth. Which ground points does the camera see?
    With ``area`` (x0, y0, width, length metres, e.g. a data set's annotated area) they are
    the area's points that land inside the image; without it, or when none does, those
    seen by the image's bottom row (an upright camera sees the ground at the bottom of its
    image, as :meth:`Camera.from_homography` assumes too). The majority decides.

    Args:
        camera: any camera.
        area: optional ground rectangle the camera is known to look at.

    Returns:
        +1 or -1.
    """
    width, height = camera.image_size
    depths = np.zeros(0)
    if area is not None:
        x0, y0, area_width, area_length = area
        grid_x, grid_y = np.meshgrid(
            np.linspace(x0, x0 + area_width, 41), np.linspace(y0, y0 + area_length, 41)
        )
        world = np.column_stack([grid_x.ravel(), grid_y.ravel(), np.ones(grid_x.size)])
        homogeneous = world @ camera.homography.T
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = homogeneous[:, :2] / homogeneous[:, 2:3]
        seen = camera.contains(pixels) & (np.abs(homogeneous[:, 2]) > 1e-12)
        depths = homogeneous[seen, 2]
    if len(depths) == 0:
        bottom = camera.undistort_pixels(
            np.column_stack([np.linspace(0, width - 1, 33), np.full(33, height - 1.0)])
        )
        bottom = bottom[np.isfinite(bottom).all(axis=1)]
        homogeneous = np.column_stack([bottom, np.ones(len(bottom))]) @ np.linalg.inv(
            camera.homography
        ).T
        depths = homogeneous[:, 2]
    return 1 if np.count_nonzero(depths > 0) >= np.count_nonzero(depths < 0) else -1


def orient_to_ground(
    camera: Camera, area: tuple[float, float, float, float] | None = None
) -> tuple[Camera, bool]:
    """The camera described so that the ground it sees lies in front of it.

    A posed camera whose visible ground has negative depth (a left-handed calibration, see
    the module notes) becomes ``R' = -R diag(1, 1, -1)``, ``t' = -t`` with its height axis
    mirrored: a proper rotation, positive depths, the same pixel for every world point, the
    same ground x, y and the same heights. A homography-only camera gets the sign of its
    homography fixed the same way. Other cameras are returned unchanged.

    Args:
        camera: the camera as read.
        area: optional ground rectangle it looks at (see :func:`ground_depth_sign`).

    Returns:
        ``(camera, converted)``; ``converted`` is True when the description was changed.
    """
    if ground_depth_sign(camera, area) > 0:
        return camera, False
    if not camera.has_pose:
        return replace(camera, homography=-camera.homography), True
    rotation, translation = camera._pose()
    assert camera.intrinsics is not None
    mirror = np.diag([1.0, 1.0, -1.0])
    return (
        Camera.from_extrinsics(
            camera.name,
            camera.intrinsics,
            -rotation @ mirror,
            -translation,
            camera.image_size,
            distortion=camera.distortion,
            height_axis=-camera.height_axis,
        ),
        True,
    )
