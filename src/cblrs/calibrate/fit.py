"""Fitting a camera to clicked points: homography, pose, focal length, k1 (see the package)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.points import Correspondences
from cblrs.calibrate.pose import FOCAL_RANGE, estimate_focal, pose_from_homography
from cblrs.camera import Camera
from cblrs.errors import CalibrationError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class Model(StrEnum):
    """What a calibration from points fits (see the module docstring)."""

    AUTO = "auto"
    HOMOGRAPHY = "homography"
    POSE = "pose"
    FOCAL = "focal"
    K1 = "k1"


MINIMUM_POINTS = {Model.HOMOGRAPHY: 4, Model.POSE: 4, Model.FOCAL: 6, Model.K1: 8}
"""Fewest correspondences each model accepts."""


@dataclass(frozen=True, eq=False)
class CalibrationFit:
    """The result of :func:`calibrate_camera`.

    Attributes:
        camera: the fitted camera (posed for pose models, homography-only otherwise).
        model: the model actually fitted (``auto`` resolved; a failed pose falls back to
            ``homography``).
        points: the correspondences.
        inliers: (N,) bool, False for RANSAC outliers (left out of the fit).
        error_px: (N,) float64 distance between each clicked pixel and its world point
            projected into the image, pixels.
        error_m: (N,) float64 distance between each world point and its clicked pixel
            projected onto the ground, metres (NaN above the horizon).
        warnings: sentences for the user (outliers, large errors, a failed pose).
        position: camera centre (x, y, height) metres, or None; for a homography fit it
            comes from :func:`pose_from_homography` when that succeeds.
        focal_px: the focal length (given, estimated or fitted), or None.
    """

    camera: Camera
    model: Model
    points: Correspondences
    inliers: BoolArray
    error_px: FloatArray
    error_m: FloatArray
    warnings: tuple[str, ...] = ()
    position: tuple[float, float, float] | None = None
    focal_px: float | None = None
    position_source: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def rms_px(self) -> float:
        """Root mean square of ``error_px`` over the inliers."""
        return float(np.sqrt(np.mean(self.error_px[self.inliers] ** 2)))

    @property
    def degrees_of_freedom(self) -> int:
        return {Model.HOMOGRAPHY: 8, Model.POSE: 6, Model.FOCAL: 7, Model.K1: 8}[self.model]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the camera in cblrs camera JSON form under ``camera``)."""
        from cblrs.calibration import camera_to_dict

        inliers = self.inliers
        return {
            "camera": camera_to_dict(self.camera),
            "model": self.model.value,
            "points": len(self.points),
            "inliers": int(inliers.sum()),
            "rms_px": self.rms_px,
            "median_error_px": float(np.median(self.error_px[inliers])),
            "median_error_m": float(np.nanmedian(self.error_m[inliers])),
            "max_error_m": float(np.nanmax(self.error_m[inliers])),
            "focal_px": self.focal_px,
            "distortion": self.camera.distortion.tolist(),
            "position": list(self.position) if self.position is not None else None,
            "position_source": self.position_source,
            "warnings": list(self.warnings),
            "per_point": [
                {
                    "name": name,
                    "u": float(u),
                    "v": float(v),
                    "x": float(x),
                    "y": float(y),
                    "inlier": bool(inlier),
                    "error_px": float(error_px),
                    "error_m": None if not np.isfinite(error_m) else float(error_m),
                }
                for name, (u, v), (x, y), inlier, error_px, error_m in zip(
                    self.points.names,
                    self.points.image_xy,
                    self.points.world_xy,
                    inliers,
                    self.error_px,
                    self.error_m,
                    strict=True,
                )
            ],
        }


# ---------------------------------------------------------------------------- fitting


def calibrate_camera(
    points: Correspondences,
    image_size: tuple[int, int],
    name: str = "camera",
    focal_px: float | None = None,
    model: Model | str = Model.AUTO,
    ransac_px: float | None = None,
    warn_px: float | None = None,
) -> CalibrationFit:
    """Fit a camera to clicked points.

    Args:
        points: at least 4 correspondences, not all on one line (in the image or on the
            ground).
        image_size: ``(width, height)`` of the camera's frames, pixels.
        name: the camera's name.
        focal_px: a focal length guess in pixels (needed by ``pose``; the starting point of
            ``focal``/``k1``; without it the focal length is estimated from the homography).
        model: ``auto`` (the richest model the points allow), ``homography``, ``pose``,
            ``focal`` or ``k1``.
        ransac_px: RANSAC inlier threshold, pixels (default 0.5 % of the image diagonal,
            11 px at 1080p); RANSAC runs from 5 points up.
        warn_px: warn when the inliers' RMS error exceeds this many pixels (default 0.25 %
            of the diagonal, 5.5 px at 1080p: a few pixels of clicking are expected).

    Returns:
        The fit, with per-point errors and warnings.

    Raises:
        CalibrationError: too few points, points on one line, a point behind the camera
            (beyond the horizon) under the fit, a model the points cannot determine, or
            a ``pose`` without a focal length; each a sentence naming ``points.source``.
    """
    model = _model(model, points.source)
    width, height = _image_size(image_size, points.source)
    diagonal = math.hypot(width, height)
    if ransac_px is not None and not (math.isfinite(ransac_px) and ransac_px > 0):
        raise CalibrationError(
            f"{points.source}: the RANSAC threshold must be a positive number of pixels, "
            f"got {ransac_px}."
        )
    # An outlier is a gross mistake (a wrong or swapped point), far beyond clicking error:
    # 11 px at 1080p by default.
    ransac_px = 0.005 * diagonal if ransac_px is None else float(ransac_px)
    warn_px = 0.0025 * diagonal if warn_px is None else float(warn_px)
    count = len(points)
    if count < MINIMUM_POINTS[Model.HOMOGRAPHY]:
        raise CalibrationError(
            f"{points.source}: {count} point{'s' if count != 1 else ''} cannot calibrate a camera; "
            "a ground homography needs at least 4 (u, v, x, y) correspondences."
        )
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise CalibrationError(
            f"{points.source}: the focal length must be a positive number of pixels, "
            f"got {focal_px}."
        )
    _check_spread(points)
    if model is not Model.AUTO and count < MINIMUM_POINTS[model]:
        fitted = {
            Model.FOCAL: "the pose and the focal length",
            Model.K1: "the pose, focal length and k1",
        }
        raise CalibrationError(
            f"{points.source}: {count} points cannot fit {fitted.get(model, model.value)} "
            f"(model {model.value} needs at least {MINIMUM_POINTS[model]}); add points or choose a "
            "simpler --model."
        )
    if model is Model.POSE and focal_px is None:
        raise CalibrationError(
            f"{points.source}: model pose keeps the focal length fixed, so it needs one "
            "(--focal PX); with 6 or more points model focal fits it."
        )
    warnings: list[str] = []
    homography, inliers = _fit_homography(points, ransac_px, warnings)
    used = int(inliers.sum())
    chosen = model
    if model is Model.AUTO:
        if used >= MINIMUM_POINTS[Model.K1]:
            chosen = Model.K1
        elif used >= MINIMUM_POINTS[Model.FOCAL]:
            chosen = Model.FOCAL
        elif focal_px is not None:
            chosen = Model.POSE
        else:
            chosen = Model.HOMOGRAPHY
    elif used < MINIMUM_POINTS[model]:
        raise CalibrationError(
            f"{points.source}: only {used} of {count} points agree with one another (the rest are "
            f"outliers), too few for model {model.value} (needs {MINIMUM_POINTS[model]})."
        )
    camera = Camera.from_homography(name, homography, (width, height))
    position: tuple[float, float, float] | None = None
    position_source = ""
    fitted_focal = focal_px
    if chosen is not Model.HOMOGRAPHY:
        try:
            camera = _fit_pose(points, inliers, (width, height), name, chosen, focal_px, homography)
            assert camera.intrinsics is not None
            fitted_focal = float(camera.intrinsics[0, 0])
            position = _position(camera)
            position_source = "pose"
        except _PoseFailure as failure:
            warnings.append(f"{points.source}: {failure}; keeping the ground homography only.")
            chosen = Model.HOMOGRAPHY
            camera = Camera.from_homography(name, homography, (width, height))
    if chosen is Model.HOMOGRAPHY:
        recovered, reason = pose_from_homography(camera.homography, (width, height), focal_px)
        if recovered is not None:
            position = _position(recovered.camera)
            fitted_focal = recovered.focal_px
            position_source = (
                "homography + estimated focal length"
                if recovered.focal_estimated
                else "homography + given focal length"
            )
        else:
            warnings.append(f"{points.source}: no camera position ({reason}).")
    error_px, error_m = point_errors(camera, points)
    if used == 4 and chosen is Model.HOMOGRAPHY:
        # 4 points give 8 equations for the homography's 8 unknowns: an exact fit.
        warnings.append(
            f"{points.source}: 4 points determine a homography exactly, so the errors say "
            "nothing about its quality; click a few more points to check it."
        )
    rms = float(np.sqrt(np.mean(error_px[inliers] ** 2)))
    if rms > warn_px:
        hint = {
            Model.HOMOGRAPHY: "a distorting lens or a sloping ground? 6 or more points fit a pose "
            "and focal length, 8 also k1",
            Model.POSE: "is the focal length right? with 6 or more points model focal fits it",
            Model.FOCAL: "a distorting lens? 8 or more points fit k1",
            Model.K1: "check the clicked points with the largest errors, or a sloping ground",
        }[chosen]
        warnings.append(
            f"{points.source}: the RMS error is {rms:.1f} px, large for model {chosen.value} "
            f"(expected under {warn_px:.1f} px); {hint}."
        )
    return CalibrationFit(
        camera=camera,
        model=chosen,
        points=points,
        inliers=inliers,
        error_px=error_px,
        error_m=error_m,
        warnings=tuple(warnings),
        position=position,
        focal_px=fitted_focal,
        position_source=position_source,
    )


def point_errors(camera: Camera, points: Correspondences) -> tuple[FloatArray, FloatArray]:
    """Per-point errors of a camera: (pixels world -> image, metres image -> ground), (N,) each."""
    projected, in_front = camera.world_to_pixel(points.world_xy)
    error_px = np.hypot(*(projected - points.image_xy).T)
    error_px[~in_front] = np.inf
    located, valid = camera.pixel_to_world(points.image_xy)
    error_m = np.hypot(*(located - points.world_xy).T)
    error_m[~valid] = np.nan
    return error_px, error_m


class _PoseFailure(Exception):
    """A pose fit that is not physically possible; the caller falls back to the homography."""


def _model(model: Model | str, source: str) -> Model:
    try:
        return Model(model)
    except ValueError:
        choices = ", ".join(item.value for item in Model)
        raise CalibrationError(
            f"{source}: unknown model {model!r}; choose one of {choices}."
        ) from None


def _image_size(image_size: tuple[int, int], source: str) -> tuple[int, int]:
    try:
        width, height = (int(value) for value in image_size)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"{source}: the image size must be (width, height) pixels."
        ) from None
    if width <= 0 or height <= 0:
        raise CalibrationError(f"{source}: the image size must be positive, got {width}x{height}.")
    return width, height


def _check_spread(points: Correspondences) -> None:
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
    matrix = _dlt_matrix(points.image_xy, points.world_xy)
    singular = np.linalg.svd(matrix, compute_uv=False)
    if singular[7] < 1e-5 * singular[0]:
        raise CalibrationError(
            f"{points.source}: the points do not pin down a homography (three of four, or all but "
            "one, lie on one line); click points spread over the ground, not along one edge."
        )


def _normalising(points: FloatArray) -> FloatArray:
    centre = points.mean(axis=0)
    scale = math.sqrt(2) / max(float(np.mean(np.hypot(*(points - centre).T))), 1e-12)
    return np.array([[scale, 0, -scale * centre[0]], [0, scale, -scale * centre[1]], [0, 0, 1]])


def _dlt_matrix(image_xy: FloatArray, world_xy: FloatArray) -> FloatArray:
    """Hartley-normalised DLT system of the homography world -> image, (2N, 9)."""
    image_norm, world_norm = _normalising(image_xy), _normalising(world_xy)
    image = np.column_stack([image_xy, np.ones(len(image_xy))]) @ image_norm.T
    world = np.column_stack([world_xy, np.ones(len(world_xy))]) @ world_norm.T
    rows = []
    for (x, y, w), (u, v, s) in zip(world, image, strict=True):
        rows.append([0, 0, 0, -s * x, -s * y, -s * w, v * x, v * y, v * w])
        rows.append([s * x, s * y, s * w, 0, 0, 0, -u * x, -u * y, -u * w])
    return np.array(rows, dtype=np.float64)


def _fit_homography(
    points: Correspondences, ransac_px: float, warnings: list[str]
) -> tuple[FloatArray, BoolArray]:
    """World -> pixel homography (sign: seen points in front) and the inlier mask."""
    world = points.world_xy.astype(np.float64)
    image = points.image_xy.astype(np.float64)
    if len(points) >= 5:
        homography, mask = cv2.findHomography(world, image, cv2.RANSAC, ransac_px)
    else:
        homography, mask = cv2.findHomography(world, image, 0)
    if homography is None or not np.all(np.isfinite(homography)):
        raise CalibrationError(f"{points.source}: OpenCV found no homography through these points.")
    inliers = np.ones(len(points), dtype=bool) if mask is None else mask.ravel().astype(bool)
    if len(points) >= 5:
        # RANSAC keeps the consensus of its best minimal sample, which with few points can
        # leave out a good one: refit on the inliers and re-admit every point within the
        # threshold until the set settles.
        for _ in range(10):
            if inliers.sum() < 4:
                break
            refit, _ = cv2.findHomography(world[inliers], image[inliers], 0)
            if refit is None:
                break
            homography = refit
            projected = cv2.perspectiveTransform(world.reshape(-1, 1, 2), refit).reshape(-1, 2)
            admitted = np.hypot(*(projected - image).T) <= ransac_px
            if np.array_equal(admitted, inliers) or admitted.sum() < 4:
                break
            inliers = admitted
    if inliers.sum() < 4:
        raise CalibrationError(
            f"{points.source}: fewer than 4 points agree with one another; check the rows."
        )
    homogeneous = np.column_stack([world, np.ones(len(world))]) @ homography.T
    depth = homogeneous[:, 2]
    if np.median(depth[inliers]) < 0:
        homography, depth = -homography, -depth
    # A point mapped through the line at infinity: with these correspondences it would have
    # to lie behind the camera (its pixel above the horizon of the others).
    behind = np.flatnonzero(inliers & (depth <= 0))
    if len(behind):
        index = int(behind[0])
        raise CalibrationError(
            f"{points.source}: {points.names[index]} (u, v = {points.image_xy[index][0]:g}, "
            f"{points.image_xy[index][1]:g}; x, y = {world[index][0]:g}, {world[index][1]:g}) "
            "lies behind the camera under the fit of the other points (beyond the horizon); "
            "check its coordinates or whether two rows are swapped."
        )
    projected = homogeneous[:, :2] / np.where(depth == 0, np.nan, depth)[:, None]
    error = np.hypot(*(projected - image).T)
    for index in np.flatnonzero(~inliers).tolist():
        where = "behind the camera" if depth[index] <= 0 else f"{error[index]:.1f} px from the fit"
        warnings.append(
            f"{points.source}: {points.names[index]} is an outlier ({where}); left out of the fit."
        )
    return homography / np.abs(homography).max(), inliers


def _fit_pose(
    points: Correspondences,
    inliers: BoolArray,
    image_size: tuple[int, int],
    name: str,
    model: Model,
    focal_px: float | None,
    homography: FloatArray,
) -> Camera:
    width, height = image_size
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    world = np.column_stack([points.world_xy[inliers], np.zeros(int(inliers.sum()))])
    image = points.image_xy[inliers]
    focal = focal_px
    if focal is None:
        focal = estimate_focal(homography, image_size)
    if focal is None:
        # No perspective to read it from (camera looking straight down): start from a
        # normal lens (about 60 degrees horizontal field of view).
        focal = 0.87 * max(width, height)
    intrinsics = np.array([[focal, 0, centre[0]], [0, focal, centre[1]], [0, 0, 1.0]])
    object_points = world.astype(np.float32).reshape(-1, 1, 3)
    image_points = image.astype(np.float32).reshape(-1, 1, 2)
    distortion = np.zeros(5)
    if model is Model.POSE:
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
        if model is Model.FOCAL:
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
            raise _PoseFailure(f"OpenCV could not fit a pose ({error.err})") from None
        rvec, tvec = np.asarray(rvecs[0], np.float64), np.asarray(tvecs[0], np.float64)
        intrinsics = np.asarray(fitted_intrinsics, dtype=np.float64)
        distortion = np.asarray(fitted_distortion, dtype=np.float64).ravel()
    fitted_focal = float(intrinsics[0, 0])
    low, high = (bound * max(width, height) for bound in FOCAL_RANGE)
    if not (low <= fitted_focal <= high):
        raise _PoseFailure(
            f"the fitted focal length ({fitted_focal:.0f} px) is not a real lens's; the points "
            "show too little perspective"
        )
    rotation = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    translation = np.asarray(tvec, dtype=np.float64).ravel()
    distortion_used = np.zeros(0)
    if model is Model.K1:
        distortion_used = np.array([distortion[0], 0.0, 0.0, 0.0])
        if not abs(distortion[0]) < 2.0:
            raise _PoseFailure(f"the fitted k1 ({distortion[0]:.3g}) is not a real lens's")
    camera = Camera.from_extrinsics(
        name, intrinsics, rotation, translation, image_size, distortion=distortion_used
    )
    _check_pose(camera, points.world_xy[inliers])
    return camera


def _solve_pnp(
    object_points: NDArray[np.float32], image_points: NDArray[np.float32], intrinsics: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Planar PnP: IPPE's two solutions, keep the one with the camera above the ground and the
    smaller error, then refine it (Levenberg-Marquardt)."""
    _, rvecs, tvecs, errors = cv2.solvePnPGeneric(
        object_points, image_points, intrinsics, None, flags=cv2.SOLVEPNP_IPPE
    )
    best: tuple[float, FloatArray, FloatArray] | None = None
    for rvec, tvec, error in zip(rvecs, tvecs, np.ravel(errors), strict=True):
        rotation = cv2.Rodrigues(rvec)[0]
        height = float((-rotation.T @ tvec.ravel())[2])
        score = float(error) + (0.0 if height > 0 else 1e9)
        if best is None or score < best[0]:
            best = (score, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64))
    if best is None:
        raise _PoseFailure("OpenCV found no pose through these points")
    _, rvec, tvec = best
    ok, rvec, tvec = cv2.solvePnP(
        object_points,
        image_points,
        intrinsics,
        None,
        rvec.copy(),
        tvec.copy(),
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        raise _PoseFailure("OpenCV could not refine the pose")
    return np.asarray(rvec, np.float64), np.asarray(tvec, np.float64)


def _check_pose(camera: Camera, world_xy: FloatArray) -> None:
    centre = camera.centre
    if not centre[2] > 0:
        raise _PoseFailure(
            f"the camera comes out {-centre[2]:.2f} m below the ground, so the world axes look "
            "left-handed (seen from above, x must turn anticlockwise onto y)"
        )
    assert camera.rotation is not None and camera.translation is not None
    world = np.column_stack([world_xy, np.zeros(len(world_xy))])
    depth = (world @ camera.rotation.T + camera.translation)[:, 2]
    if np.any(depth <= 0):
        raise _PoseFailure("some points come out behind the fitted camera")


def _position(camera: Camera) -> tuple[float, float, float]:
    centre = camera.centre
    return (float(centre[0]), float(centre[1]), float(centre[2]))
