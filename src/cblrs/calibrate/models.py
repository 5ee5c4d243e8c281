"""Fitting one model to the inlier points: a linear or pixel-only start, then :func:`refine`.

Each model starts where OpenCV puts it (``findHomography``; planar ``solvePnP`` (IPPE) with a
given focal length; ``calibrateCamera`` with a planar rig, fixed principal point and square
pixels for the focal length and k1) and is then refined under click and ground errors
(:mod:`cblrs.calibrate.refine`). A fit that is physically impossible raises
:class:`ModelFailure` with the reason, which the caller reports.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.pose import FOCAL_RANGE, estimate_focal
from cblrs.calibrate.refine import (
    FOCAL,
    HOMOGRAPHY,
    K1,
    POSE,
    Parameterisation,
    PointNoise,
    Refined,
    refine,
)
from cblrs.camera import Camera

FloatArray = NDArray[np.float64]

# |k1| beyond this is no real lens (a fisheye needs another model).
K1_LIMIT = 2.0


class ModelFailure(Exception):
    """A fit that is not physically possible; the message says why (a clause, no full stop)."""


def fit_model(
    model: str,
    image_xy: FloatArray,
    world_xy: FloatArray,
    image_size: tuple[int, int],
    noise: PointNoise,
    homography: FloatArray,
    focal_px: float | None = None,
    start_on: NDArray[np.bool_] | None = None,
) -> Refined:
    """Fit ``model`` to the points (all of them inliers).

    Args:
        model: ``homography``, ``pose``, ``focal`` or ``k1``.
        image_xy: (N, 2) pixels.
        world_xy: (N, 2) ground metres.
        image_size: (width, height).
        noise: the points' noise.
        homography: (3, 3) a world -> pixel homography of these points (the start of the
            homography and of the focal length estimate).
        focal_px: the focal length (``pose``), or the focal length guess (``focal``, ``k1``).
        start_on: (N,) bool, the points to start from (the rest may hold gross errors: the
            refinement is then robust, see :func:`refine`); None for all (no outliers).

    Raises:
        ModelFailure: the fitted camera is not a real one (below the ground, points behind
            it, an absurd focal length or k1).
    """
    subset = np.ones(len(image_xy), dtype=bool) if start_on is None else start_on
    if model == HOMOGRAPHY:
        start = Camera.from_homography("start", homography, image_size)
    else:
        start = _start_pose(
            model, image_xy[subset], world_xy[subset], image_size, homography, focal_px
        )
    parameterisation, params = Parameterisation.of_camera(model, start, world_xy, image_xy)
    refined = refine(
        parameterisation, params, image_xy, world_xy, noise, robust=start_on is not None
    )
    check(refined, world_xy[subset])
    return refined


def check(refined: Refined, world_xy: FloatArray) -> None:
    """Raise :class:`ModelFailure` unless the refined model is a real camera seeing the points."""
    parameterisation = refined.parameterisation
    _, depth = parameterisation.project(refined.params, world_xy)
    if parameterisation.model == HOMOGRAPHY:
        if not (np.all(depth > 0) or np.all(depth < 0)):
            raise ModelFailure("the points lie on both sides of the fitted horizon")
        return
    width, height = parameterisation.image_size
    camera = refined.camera("check")
    assert camera.intrinsics is not None
    focal = float(camera.intrinsics[0, 0])
    low, high = (bound * max(width, height) for bound in FOCAL_RANGE)
    if not (low <= focal <= high):
        raise ModelFailure(
            f"the fitted focal length ({focal:.0f} px) is not a real lens's; the points show "
            "too little perspective"
        )
    if parameterisation.model == K1:
        k1 = float(refined.params[7])
        # The lens must map radius to radius monotonically over the whole frame:
        # d/dr [r (1 + k1 r^2)] = 1 + 3 k1 r^2 > 0 out to the farthest corner.
        corner = math.hypot(width / 2.0, height / 2.0) / focal
        if not (abs(k1) < K1_LIMIT and 1 + 3 * k1 * corner**2 > 0):
            raise ModelFailure(f"the fitted k1 ({k1:.3g}) is not a real lens's")
    centre = camera.centre
    if not centre[2] > 0:
        raise ModelFailure(
            f"the camera comes out {-centre[2]:.2f} m below the ground, so the world axes look "
            "left-handed (seen from above, x must turn anticlockwise onto y)"
        )
    if np.any(depth <= 0):
        raise ModelFailure("some points come out behind the fitted camera")


def _start_pose(
    model: str,
    image_xy: FloatArray,
    world_xy: FloatArray,
    image_size: tuple[int, int],
    homography: FloatArray,
    focal_px: float | None,
) -> Camera:
    width, height = image_size
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    focal = focal_px if focal_px is not None else estimate_focal(homography, image_size)
    if focal is None:
        # No perspective to read it from (camera looking straight down): start from a
        # normal lens (about 60 degrees horizontal field of view).
        focal = 0.87 * max(width, height)
    intrinsics = np.array([[focal, 0, centre[0]], [0, focal, centre[1]], [0, 0, 1.0]])
    object_points = np.column_stack([world_xy, np.zeros(len(world_xy))])
    object_points = object_points.astype(np.float32).reshape(-1, 1, 3)
    image_points = image_xy.astype(np.float32).reshape(-1, 1, 2)
    distortion = np.zeros(5)
    if model == POSE or len(world_xy) < 6:
        # calibrateCamera wants 6 points or more (the cross-validation folds may hold fewer).
        rvec, tvec = _solve_pnp(object_points, image_points, intrinsics)
    else:
        flags = (
            cv2.CALIB_USE_INTRINSIC_GUESS
            | cv2.CALIB_FIX_PRINCIPAL_POINT
            | cv2.CALIB_FIX_ASPECT_RATIO
            | cv2.CALIB_ZERO_TANGENT_DIST
            | cv2.CALIB_FIX_K2
            | cv2.CALIB_FIX_K3
        )
        if model == FOCAL:
            flags |= cv2.CALIB_FIX_K1
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
        try:
            _, fitted_intrinsics, fitted_distortion, rvecs, tvecs = cv2.calibrateCamera(
                [object_points],
                [image_points],
                (width, height),
                intrinsics.copy(),
                distortion.copy(),
                flags=flags,
                criteria=criteria,
            )
        except cv2.error as error:
            raise ModelFailure(f"OpenCV could not fit a pose ({error.err})") from None
        rvec, tvec = np.asarray(rvecs[0], np.float64), np.asarray(tvecs[0], np.float64)
        intrinsics = np.asarray(fitted_intrinsics, dtype=np.float64)
        distortion = np.asarray(fitted_distortion, dtype=np.float64).ravel()
        if not (np.all(np.isfinite(intrinsics)) and intrinsics[0, 0] > 0):
            raise ModelFailure("OpenCV could not fit a pose")
    rotation = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    translation = np.asarray(tvec, dtype=np.float64).ravel()
    # Start k1 inside the range a real lens has; the refinement moves it if the points say so.
    k1 = float(np.clip(distortion[0], -0.5, 0.5)) if model == K1 else 0.0
    return Camera.from_extrinsics(
        "start",
        intrinsics,
        rotation,
        translation,
        image_size,
        distortion=np.array([k1, 0.0, 0.0, 0.0]) if model == K1 else None,
    )


def _solve_pnp(
    object_points: NDArray[np.float32], image_points: NDArray[np.float32], intrinsics: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Planar PnP: IPPE's two solutions, keep the one with the camera above the ground and the
    smaller error."""
    try:
        _, rvecs, tvecs, errors = cv2.solvePnPGeneric(
            object_points, image_points, intrinsics, None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error as error:
        raise ModelFailure(f"OpenCV could not fit a pose ({error.err})") from None
    best: tuple[float, FloatArray, FloatArray] | None = None
    for rvec, tvec, residual in zip(rvecs, tvecs, np.ravel(errors), strict=True):
        rotation = cv2.Rodrigues(rvec)[0]
        height = float((-rotation.T @ tvec.ravel())[2])
        score = float(residual) + (0.0 if height > 0 else 1e9)
        if best is None or score < best[0]:
            best = (score, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64))
    if best is None:
        raise ModelFailure("OpenCV found no pose through these points")
    return best[1], best[2]
