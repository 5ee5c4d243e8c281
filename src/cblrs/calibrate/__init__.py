"""Calibration from clicked points: image <-> ground correspondences -> a camera.

People who deploy cameras rarely have a lab calibration. They have a frame from each camera
and a site plan, and can click points they find in both. From ``N`` such correspondences
(pixel ``(u, v)`` <-> ground ``(x, y)`` metres on the plane z = 0) this module fits, unlocking
parameters only as the points allow (the thresholds of the closest open-source peer, Intel
SceneScape):

============  ==========  ==================================================================
model         points      what is fitted
============  ==========  ==================================================================
homography    >= 4        the ground homography (OpenCV ``findHomography``; RANSAC from 5)
pose          >= 4        rotation and position with a given focal length (``solvePnP``)
focal         >= 6        + the focal length (``calibrateCamera``, planar rig, fixed
                          principal point, square pixels, no tangential distortion)
k1            >= 8        + the first radial distortion coefficient
============  ==========  ==================================================================

``auto`` picks the richest model the points allow. A pose needs the camera above the ground
and every point in front of it; a fit that fails that, or whose focal length is absurd,
falls back to the homography with a warning. A homography alone still gives the camera's
position when the focal length is known or can be estimated from it
(:func:`pose_from_homography`, the issue's "camera without a full pose").

Every fit reports each point's error both ways: the world point projected into the image
(pixels) and the clicked pixel projected onto the ground (metres).

Example:
    >>> import numpy as np
    >>> from cblrs.camera import Camera
    >>> truth = Camera.from_pose("c", (0, -10, 6), 90, 30, 1000, (1280, 720))
    >>> world = np.array([[x, y] for x in (-4, 0, 4) for y in (0, 5, 10)], float)
    >>> pixels, _ = truth.world_to_pixel(world)
    >>> fit = calibrate_camera(Correspondences(pixels, world), (1280, 720), "c")
    >>> fit.model.value, round(float(fit.camera.centre[2]), 3)
    ('k1', 6.0)
"""

from cblrs.calibrate.fit import (
    MINIMUM_POINTS,
    CalibrationFit,
    Model,
    calibrate_camera,
    point_errors,
)
from cblrs.calibrate.points import Correspondences
from cblrs.calibrate.pose import RecoveredPose, estimate_focal, pose_from_homography

__all__ = [
    "MINIMUM_POINTS",
    "CalibrationFit",
    "Correspondences",
    "Model",
    "RecoveredPose",
    "calibrate_camera",
    "estimate_focal",
    "point_errors",
    "pose_from_homography",
]
