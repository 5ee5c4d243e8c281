"""Fitting a camera to clicked points: homography, pose, focal length, k1 (see the package)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.checks import check_spread, image_size_of
from cblrs.calibrate.models import ModelFailure, fit_model
from cblrs.calibrate.plausible import MAX_HEIGHT_M, check_handedness, check_in_image, check_scale
from cblrs.calibrate.points import Correspondences
from cblrs.calibrate.pose import pose_from_homography
from cblrs.calibrate.refine import PointNoise, Refined, normalised_errors
from cblrs.calibrate.robust import OUTLIER_DISTANCE, consensus, homography_distances
from cblrs.calibrate.select import ORDER, HeldOut, choose, cross_validate
from cblrs.calibrate.uncertainty import Coverage, ErrorMap, coverage, error_map, ground_error
from cblrs.calibration import camera_to_dict
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

# The global test of a fit: its squared normalised errors exceed what the stated noise
# explains with this probability only.
_LARGE_ERROR_PROBABILITY = 1e-3
# Warn when more than this share of the image between the points is poorly constrained
# (far ground is a thin band of rows that may hold most of the people).
_POOR_SHARE = 0.02


@dataclass(frozen=True, eq=False)
class CalibrationFit:
    """The result of :func:`calibrate_camera`.

    Attributes:
        camera: the fitted camera (posed for pose models, homography-only otherwise).
        model: the model actually fitted (``auto`` resolved; a failed pose falls back to
            ``homography``).
        points: the correspondences.
        inliers: (N,) bool, False for outliers (left out of the fit).
        error_px: (N,) float64 distance between each clicked pixel and its world point
            projected into the image, pixels.
        error_m: (N,) float64 distance between each world point and its clicked pixel
            projected onto the ground, metres (NaN above the horizon).
        warnings: sentences for the user (outliers, large errors, a failed pose).
        position: camera centre (x, y, height) metres, or None; for a homography fit it
            comes from a fitted pose or :func:`pose_from_homography`.
        focal_px: the focal length (given, estimated or fitted), or None.
        position_source: how the position was found.
        noise: the points' stated noise.
        held_out: per candidate model, how it predicts each inlier left out of its fit
            (empty when only one model was possible).
        refined: the chosen model's refinement (parameters and their covariance).
        error_map: the predicted ground error over the image
            (:mod:`cblrs.calibrate.uncertainty`), None without a refinement.
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
    noise: PointNoise = field(default_factory=PointNoise)
    held_out: Mapping[str, HeldOut] = field(default_factory=dict)
    refined: Refined | None = None
    error_map: ErrorMap | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def rms_px(self) -> float:
        """Root mean square of ``error_px`` over the inliers."""
        return float(np.sqrt(np.mean(self.error_px[self.inliers] ** 2)))

    @property
    def coverage(self) -> Coverage | None:
        """How much of the image between the points is poorly constrained (None without
        an error map)."""
        if self.error_map is None:
            return None
        return coverage(self.error_map, self.points.image_xy[self.inliers])

    def predicted_error_m(self, pixels: FloatArray) -> FloatArray:
        """(N,) predicted RMS ground error (metres) of locating raw pixels (N, 2) with this
        fit; NaN where no ground is seen (see :func:`cblrs.calibrate.uncertainty.ground_error`)."""
        if self.refined is None:
            return np.full(len(pixels), np.nan)
        return ground_error(self.refined, pixels)

    @property
    def degrees_of_freedom(self) -> int:
        return {Model.HOMOGRAPHY: 8, Model.POSE: 6, Model.FOCAL: 7, Model.K1: 8}[self.model]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the camera in cblrs camera JSON form under ``camera``)."""

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
            "noise": {"click_px": self.noise.click_px, "ground_m": self.noise.ground_m},
            "predicted_error": _coverage_dict(self.coverage),
            "held_out": {
                model: {
                    "score": result.score,
                    "standard_error": result.standard_error,
                    "rms_px": _finite_rms(result.error_px),
                    "median_m": _nan_median(result.error_m),
                }
                for model, result in self.held_out.items()
            },
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
    click_px: float = 2.0,
    ground_m: float = 0.1,
    left_handed: bool = False,
    max_height_m: float = MAX_HEIGHT_M,
) -> CalibrationFit:
    """Fit a camera to clicked points.

    Args:
        points: at least 4 correspondences, not all on one line (in the image or on the
            ground).
        image_size: ``(width, height)`` of the camera's frames, pixels.
        name: the camera's name.
        focal_px: a focal length guess in pixels (needed by ``pose``; the starting point of
            ``focal``/``k1``; without it the focal length is estimated from the homography).
        model: ``auto`` (the model that best predicts points left out of the fit, among
            those the points allow), ``homography``, ``pose``, ``focal`` or ``k1``.
        ransac_px: an outlier threshold in pixels instead of the test under the stated noise
            (a point is an outlier when the noise explains its error with a chance under
            1 in 1000); outliers are looked for from 5 points up.
        warn_px: warn when the inliers' RMS error exceeds this many pixels instead of when
            the stated noise does not explain the errors.
        click_px: how far a click may miss its pixel, one standard deviation per axis.
        ground_m: how far a point's ground position may be off (the site plan's accuracy),
            metres, one standard deviation per axis.
        left_handed: the world's axes are left-handed on purpose; otherwise mirrored points
            (``u, v`` or ``x, y`` swapped) are refused.
        max_height_m: a fit that puts the camera higher is refused (ground positions in
            centimetres or map pixels read as metres).

    Returns:
        The fit, with per-point errors and warnings.

    Raises:
        CalibrationError: too few points, points on one line or outside the image, a point
            behind the camera (beyond the horizon) under the fit, a model the points cannot
            determine, a ``pose`` without a focal length, or an implausible camera (mirrored,
            too high: :mod:`~cblrs.calibrate.plausible`); each a sentence naming
            ``points.source``.
    """
    model = _model(model, points.source)
    width, height = image_size_of(image_size, points.source)
    for value, what in (
        (ransac_px, "the RANSAC threshold must be a positive number of pixels"),
        (warn_px, "the warning threshold must be a positive number of pixels"),
        (click_px, "the click noise must be a positive number of pixels"),
        (ground_m, "the ground noise must be a positive number of metres"),
        (focal_px, "the focal length must be a positive number of pixels"),
        (max_height_m, "the largest camera height must be a positive number of metres"),
    ):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise CalibrationError(f"{points.source}: {what}, got {value}.")
    noise = PointNoise(float(click_px), float(ground_m))
    count = len(points)
    if count < MINIMUM_POINTS[Model.HOMOGRAPHY]:
        raise CalibrationError(
            f"{points.source}: {count} point{'s' if count != 1 else ''} cannot calibrate a camera; "
            "a ground homography needs at least 4 (u, v, x, y) correspondences."
        )
    check_spread(points)
    check_in_image(points, (width, height))
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
    homography, inliers = _consensus(points, noise, ransac_px)
    check_handedness(points, homography, inliers, left_handed)
    used = int(inliers.sum())
    if model is not Model.AUTO and used < MINIMUM_POINTS[model]:
        raise CalibrationError(
            f"{points.source}: only {used} of {count} points agree with one another (the rest are "
            f"outliers), too few for model {model.value} (needs {MINIMUM_POINTS[model]})."
        )
    fits, failures, inliers = _fit_candidates(
        points, inliers, (width, height), noise, homography, focal_px, model, ransac_px
    )
    _report_outliers(points, inliers, fits, noise, warnings)
    held_out: dict[str, HeldOut] = {}
    if model is Model.AUTO and len(fits) > 1:
        image, world = points.image_xy[inliers], points.world_xy[inliers]
        for candidate, refined in fits.items():
            result = cross_validate(refined, image, world, noise)
            if result is not None:
                held_out[candidate] = result
        chosen_name = choose(held_out) or next(m for m in reversed(ORDER) if m in fits)
    elif model is Model.AUTO:
        chosen_name = next(iter(fits))
    else:
        chosen_name = model.value if model.value in fits else Model.HOMOGRAPHY.value
    chosen = Model(chosen_name)
    poses = [candidate for candidate in fits if candidate != Model.HOMOGRAPHY.value]
    if chosen is Model.HOMOGRAPHY and failures and not poses:
        # Say why no pose: the reason of the richest pose model tried.
        warnings.append(f"{points.source}: {failures[-1]}; keeping the ground homography only.")
    refined = fits[chosen.value]
    camera = refined.camera(name)
    position: tuple[float, float, float] | None = None
    position_source = ""
    fitted_focal = focal_px
    if chosen is not Model.HOMOGRAPHY:
        assert camera.intrinsics is not None
        fitted_focal = float(camera.intrinsics[0, 0])
        position = _position(camera)
        position_source = "pose"
    elif poses:
        # The homography maps the ground best, but a pose fitted too: it places the camera.
        pose_name = choose({key: held_out[key] for key in poses if key in held_out}) or poses[-1]
        posed = fits[pose_name].camera(name)
        assert posed.intrinsics is not None
        position, fitted_focal = _position(posed), float(posed.intrinsics[0, 0])
        position_source = f"pose (model {pose_name})"
    else:
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
    check_scale(points, None if position is None else position[2], max_height_m)
    error_px, error_m = point_errors(camera, points)
    if used == 4 and chosen is Model.HOMOGRAPHY:
        # 4 points give 8 equations for the homography's 8 unknowns: an exact fit.
        warnings.append(
            f"{points.source}: 4 points determine a homography exactly, so the errors say "
            "nothing about its quality; click a few more points to check it."
        )
    large = _large_error(refined, error_px[inliers], noise, warn_px, (width, height))
    if large is not None:
        hint = {
            Model.HOMOGRAPHY: "a distorting lens or a sloping ground? 6 or more points fit a pose "
            "and focal length, 8 also k1",
            Model.POSE: "is the focal length right? with 6 or more points model focal fits it",
            Model.FOCAL: "a distorting lens? 8 or more points fit k1",
            Model.K1: "check the clicked points with the largest errors, or a sloping ground",
        }[chosen]
        warnings.append(f"{points.source}: {large}; {hint}.")
    errors = error_map(refined, (width, height))
    cover = coverage(errors, points.image_xy[inliers])
    if cover.share > _POOR_SHARE and cover.rows is not None and cover.columns is not None:
        warnings.append(
            f"{points.source}: on {cover.share:.0%} of the image from the highest point down, "
            f"the predicted ground error exceeds {cover.limit_m:g} m (mostly rows "
            f"{cover.rows[0]:.0f}-{cover.rows[1]:.0f}, columns {cover.columns[0]:.0f}-"
            f"{cover.columns[1]:.0f}); click more points there."
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
        noise=noise,
        held_out=held_out,
        refined=refined,
        error_map=errors,
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


# ---------------------------------------------------------------------------- steps


def _consensus(
    points: Correspondences, noise: PointNoise, ransac_px: float | None
) -> tuple[FloatArray, BoolArray]:
    """A homography of the points and the inliers; refuses points behind the camera."""
    world, image = points.world_xy, points.image_xy
    if len(points) >= 5:
        homography, inliers = consensus(image, world, noise, ransac_px)
    else:
        exact, _ = cv2.findHomography(world, image, 0)
        homography = np.full((3, 3), np.nan) if exact is None else np.asarray(exact, np.float64)
        inliers = np.ones(len(points), dtype=bool)
    if not np.all(np.isfinite(homography)):
        raise CalibrationError(f"{points.source}: OpenCV found no homography through these points.")
    if inliers.sum() < 4:
        raise CalibrationError(
            f"{points.source}: fewer than 4 points agree with one another; check the rows."
        )
    _, _, depth = homography_distances(homography, image, world, noise)
    # A point mapped through the line at infinity: with these correspondences it would have
    # to lie behind the camera (its pixel above the horizon of the others).
    behind = np.flatnonzero(inliers & (depth <= 0))
    if len(behind):
        index = int(behind[0])
        raise CalibrationError(
            f"{points.source}: {points.names[index]} (u, v = {image[index][0]:g}, "
            f"{image[index][1]:g}; x, y = {world[index][0]:g}, {world[index][1]:g}) "
            "lies behind the camera under the fit of the other points (beyond the horizon); "
            "check its coordinates or whether two rows are swapped."
        )
    return homography, inliers


def _candidates(model: Model, used: int, focal_px: float | None) -> list[str]:
    """Models to fit, simplest first; the homography always (the fallback of a failed pose)."""
    if model is not Model.AUTO:
        wanted = [model.value]
    else:
        wanted = [Model.POSE.value] if focal_px is not None else []
        wanted += [
            candidate.value
            for candidate in (Model.FOCAL, Model.K1)
            if used >= MINIMUM_POINTS[candidate]
        ]
    return [Model.HOMOGRAPHY.value] + [name for name in wanted if name != Model.HOMOGRAPHY.value]


def _fit_candidates(
    points: Correspondences,
    inliers: BoolArray,
    image_size: tuple[int, int],
    noise: PointNoise,
    homography: FloatArray,
    focal_px: float | None,
    model: Model,
    ransac_px: float | None,
) -> tuple[dict[str, Refined], list[str], BoolArray]:
    """Fit every candidate model on the inliers; with 5 points or more, re-admit or drop
    points under the richest model that fits (a lens's distortion is no outlier) until the
    inliers settle.

    Returns:
        ``(fits by model name, reasons of the pose models that failed, inliers)``.
    """
    consensus_inliers = inliers
    if not inliers.all():
        # The consensus is a homography's: a distorting lens moves the frame's edges off it.
        # The richest model the points allow, fitted robustly to all of them, says which
        # points are really beyond the noise.
        richest = _candidates(model, len(points), focal_px)[-1]
        if richest != Model.HOMOGRAPHY.value:
            try:
                robust = fit_model(
                    richest,
                    points.image_xy,
                    points.world_xy,
                    image_size,
                    noise,
                    homography,
                    focal_px,
                    start_on=inliers,
                )
                admitted = _outlier_scores(robust, points, noise, ransac_px) <= OUTLIER_DISTANCE
                if admitted.sum() > inliers.sum():
                    inliers = admitted
            except ModelFailure:
                pass
    settled: tuple[dict[str, Refined], list[str], BoolArray] | None = None
    for _ in range(4):
        image, world = points.image_xy[inliers], points.world_xy[inliers]
        fits: dict[str, Refined] = {}
        failures: list[str] = []
        for candidate in _candidates(model, int(inliers.sum()), focal_px):
            try:
                fits[candidate] = fit_model(
                    candidate, image, world, image_size, noise, homography, focal_px
                )
            except ModelFailure as failure:
                failures.append(str(failure))
        if not fits:
            if settled is not None:
                return settled
            if not np.array_equal(inliers, consensus_inliers):
                inliers = consensus_inliers
                continue
            raise CalibrationError(
                f"{points.source}: no model fits these points ({failures[0]}); check the rows."
            )
        settled = (fits, failures, inliers)
        if len(points) < 5:
            break
        richest_fit = fits[list(fits)[-1]]
        admitted = _outlier_scores(richest_fit, points, noise, ransac_px) <= OUTLIER_DISTANCE
        if np.array_equal(admitted, inliers) or admitted.sum() < 4:
            break
        if model is not Model.AUTO and admitted.sum() < MINIMUM_POINTS[model]:
            break
        inliers = admitted
    assert settled is not None
    return settled


def _outlier_scores(
    refined: Refined, points: Correspondences, noise: PointNoise, ransac_px: float | None
) -> FloatArray:
    parameterisation = refined.parameterisation
    if ransac_px is None:
        return normalised_errors(
            parameterisation, refined.params, points.image_xy, points.world_xy, noise
        )
    predicted, depth = parameterisation.project(refined.params, points.world_xy)
    error = np.where(depth > 0, np.hypot(*(predicted - points.image_xy).T), np.inf)
    return (error / ransac_px) ** 2 * OUTLIER_DISTANCE


def _report_outliers(
    points: Correspondences,
    inliers: BoolArray,
    fits: Mapping[str, Refined],
    noise: PointNoise,
    warnings: list[str],
) -> None:
    if inliers.all():
        return
    refined = fits[list(fits)[-1]]
    predicted, depth = refined.parameterisation.project(refined.params, points.world_xy)
    error = np.hypot(*(predicted - points.image_xy).T)
    for index in np.flatnonzero(~inliers).tolist():
        where = "behind the camera" if depth[index] <= 0 else f"{error[index]:.1f} px from the fit"
        warnings.append(
            f"{points.source}: {points.names[index]} is an outlier ({where}); left out of the fit."
        )


def _large_error(
    refined: Refined,
    error_px: FloatArray,
    noise: PointNoise,
    warn_px: float | None,
    image_size: tuple[int, int],
) -> str | None:
    """The sentence on errors too large for the model, or None."""
    rms = float(np.sqrt(np.mean(error_px**2)))
    model = refined.parameterisation.model
    if warn_px is not None:
        if rms <= warn_px:
            return None
        return (
            f"the RMS error is {rms:.1f} px, large for model {model} "
            f"(expected under {warn_px:.1f} px)"
        )
    redundancy = refined.redundancy
    if redundancy <= 0:
        return None
    from scipy.stats import chi2  # lazy: ~0.4 s of CPU, paid by every process loading a site
    if refined.chi_square <= chi2.ppf(1 - _LARGE_ERROR_PROBABILITY, redundancy):
        return None
    factor = math.sqrt(refined.chi_square / redundancy)
    return (
        f"the RMS error is {rms:.1f} px, large for model {model}: the points disagree "
        f"{factor:.1f} times more than {noise.click_px:g} px clicks and {noise.ground_m:g} m on "
        "the ground explain"
    )


def _coverage_dict(result: Coverage | None) -> dict[str, Any] | None:
    if result is None:
        return None
    return {
        "median_m": None if not math.isfinite(result.median_m) else result.median_m,
        "limit_m": result.limit_m,
        "share_over_limit": result.share,
        "rows": list(result.rows) if result.rows else None,
        "columns": list(result.columns) if result.columns else None,
        "reliable_below_row": result.reliable_below_row,
    }


def _finite_rms(values: FloatArray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(finite**2))) if len(finite) else None


def _nan_median(values: FloatArray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if len(finite) else None


def _model(model: Model | str, source: str) -> Model:
    try:
        return Model(model)
    except ValueError:
        choices = ", ".join(item.value for item in Model)
        raise CalibrationError(
            f"{source}: unknown model {model!r}; choose one of {choices}."
        ) from None


def _position(camera: Camera) -> tuple[float, float, float]:
    centre = camera.centre
    return (float(centre[0]), float(centre[1]), float(centre[2]))
