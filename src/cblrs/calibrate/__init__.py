"""Calibration from clicked points: image <-> ground correspondences -> a camera.

People who deploy cameras rarely have a lab calibration. They have a frame from each camera
and a site plan, and can click points they find in both. From ``N`` such correspondences
(pixel ``(u, v)`` <-> ground ``(x, y)`` metres on the plane z = 0) this module fits, unlocking
parameters only as the points allow (the thresholds of the closest open-source peer, Intel
SceneScape):

============  ==========  ==================================================================
model         points      what is fitted
============  ==========  ==================================================================
homography    >= 4        the ground homography
pose          >= 4        rotation and position with a given focal length
focal         >= 6        + the focal length (principal point at the image centre, square
                          pixels, no skew)
k1            >= 8        + the first radial distortion coefficient
============  ==========  ==================================================================

How (one module each):

- :mod:`~cblrs.calibrate.refine`: a clicked point is off in the image (``click_px``) and on
  the plan (``ground_m``); every model is fitted to both (least squares over the model and each
  point's true ground position), so near points, whose plan error is many pixels, do not pull
  the far ground away.
- :mod:`~cblrs.calibrate.robust`: outliers are points whose error that noise does not explain
  at their place in the image (MSAC over 4-point homographies, then re-admission under the
  richest model, so a distorting lens's edges are no outliers).
- :mod:`~cblrs.calibrate.models`: each model starts from OpenCV (``findHomography``, IPPE
  ``solvePnP``, ``calibrateCamera`` with a planar rig) and is refined; a fit that is no real
  camera (below the ground, an absurd focal length or k1) fails with the reason.
- :mod:`~cblrs.calibrate.select`: ``auto`` cross-validates the models the points allow and
  keeps the simplest within one standard error of the best held-out score.
- :mod:`~cblrs.calibrate.uncertainty`: the fit's parameter covariance carried to every pixel:
  where the calibration can be trusted, and where more points are needed.

A homography alone still gives the camera's position when the focal length is known or can be
estimated from it (:func:`pose_from_homography`, the issue's "camera without a full pose").
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
    ('focal', 6.0)
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
from cblrs.calibrate.refine import PointNoise
from cblrs.calibrate.uncertainty import POORLY_CONSTRAINED_M, Coverage, ErrorMap

__all__ = [
    "MINIMUM_POINTS",
    "POORLY_CONSTRAINED_M",
    "CalibrationFit",
    "Correspondences",
    "Coverage",
    "ErrorMap",
    "Model",
    "PointNoise",
    "RecoveredPose",
    "calibrate_camera",
    "estimate_focal",
    "point_errors",
    "pose_from_homography",
]
