"""Where a clicked calibration can be trusted: its parameters' uncertainty carried to the ground.

A fit is only as good as its points reach: between the clicked points it interpolates, away
from them it extrapolates, and near the horizon one pixel spans metres. The refinement gives
the covariance of the model's parameters (:attr:`cblrs.calibrate.refine.Refined.covariance`);
carried through the pixel -> ground mapping it predicts, for every pixel, how far the fitted
camera may put what that pixel sees (the RMS of the 2-D ground error, metres). On WILDTRACK
this prediction tracks the real localisation error (see docs/sites.md, "How good is a
clicked calibration?"), so it tells the user where to click more points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.calibrate.refine import Refined

FloatArray = NDArray[np.float64]

POORLY_CONSTRAINED_M = 0.5
"""Predicted ground error above which a part of the image is "poorly constrained" (metres):
about a person's width, where tracks of neighbours start to swap."""


def ground_error(refined: Refined, pixels: FloatArray) -> FloatArray:
    """Predicted RMS ground error (metres) of locating each pixel with the fitted model.

    Args:
        refined: the fitted model.
        pixels: (N, 2) raw pixels.

    Returns:
        (N,) metres; NaN for pixels that do not see the ground.
    """
    parameterisation, params = refined.parameterisation, refined.params
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    base, valid = parameterisation.camera(params, "error").pixel_to_world(pixels)
    covariance = refined.covariance
    spread = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    gradient = np.zeros((len(pixels), 2, parameterisation.size))
    for column in range(parameterisation.size):
        # Central differences over half a standard deviation: linear where it matters.
        step = 0.5 * spread[column] if spread[column] > 0 else 1e-6
        ahead, behind = params.copy(), params.copy()
        ahead[column] += step
        behind[column] -= step
        forward, _ = parameterisation.camera(ahead, "error").pixel_to_world(pixels)
        backward, _ = parameterisation.camera(behind, "error").pixel_to_world(pixels)
        gradient[:, :, column] = (forward - backward) / (2 * step)
    ground_covariance = gradient @ covariance @ gradient.transpose(0, 2, 1)
    error = np.sqrt(np.clip(np.trace(ground_covariance, axis1=1, axis2=2), 0.0, None))
    error[~valid | ~np.isfinite(error) | ~np.isfinite(base).all(axis=1)] = np.nan
    return error


@dataclass(frozen=True, eq=False)
class ErrorMap:
    """:func:`ground_error` on a grid of pixels.

    Attributes:
        u: (C,) pixel columns of the grid.
        v: (R,) pixel rows of the grid.
        error_m: (R, C) predicted ground error, metres (NaN where no ground is seen).
    """

    u: FloatArray
    v: FloatArray
    error_m: FloatArray

    def full(self, image_size: tuple[int, int]) -> NDArray[np.float32]:
        """(H, W) float32 error at every pixel (nearest grid cell's, NaN kept)."""
        width, height = image_size
        step = float(self.u[1] - self.u[0]) if len(self.u) > 1 else float(2 * self.u[0])
        columns = np.clip(np.round((np.arange(width) - self.u[0]) / step), 0, len(self.u) - 1)
        rows = np.clip(np.round((np.arange(height) - self.v[0]) / step), 0, len(self.v) - 1)
        return self.error_m[np.ix_(rows.astype(int), columns.astype(int))].astype(np.float32)


def error_map(refined: Refined, image_size: tuple[int, int], cells: int = 64) -> ErrorMap:
    """:func:`ground_error` on a grid of about ``cells`` columns over the image."""
    width, height = image_size
    step = max(width, height) / cells
    u = np.arange(step / 2, width, step)
    v = np.arange(step / 2, height, step)
    grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    return ErrorMap(u, v, ground_error(refined, grid).reshape(len(v), len(u)))


@dataclass(frozen=True)
class Coverage:
    """How much of the image between the clicked points is poorly constrained.

    Attributes:
        median_m: median predicted error over the ground seen from the highest clicked
            point's row down to the bottom of the frame, metres.
        share: fraction of that ground whose predicted error exceeds ``limit_m``.
        limit_m: the limit.
        rows: (first, last) image rows of most of the poorly constrained part (10th and 90th
            percentile), or None when there is none.
        columns: the same for columns.
        reliable_below_row: the image row below which every grid row's median predicted
            error is within ``limit_m`` (above it the error grows towards the horizon), or
            None when the whole seen ground is within it.
    """

    median_m: float
    share: float
    limit_m: float
    rows: tuple[float, float] | None
    columns: tuple[float, float] | None
    reliable_below_row: float | None = None


def coverage(
    errors: ErrorMap, image_xy: FloatArray, limit_m: float = POORLY_CONSTRAINED_M
) -> Coverage:
    """Summarise an :class:`ErrorMap` over the part of the image the points span in height
    (above the highest click everything is extrapolation, up to the horizon)."""
    reliable_below_row = None
    step = float(errors.v[1] - errors.v[0]) if len(errors.v) > 1 else 0.0
    with np.errstate(all="ignore"):
        for index in range(len(errors.v) - 1, -1, -1):
            row = errors.error_m[index]
            # A row that sees no ground is past the horizon: as bad as it gets.
            if not np.isfinite(row).any() or np.nanmedian(row) > limit_m:
                reliable_below_row = float(errors.v[index] + step / 2)
                break
    top = float(np.min(image_xy[:, 1])) if len(image_xy) else 0.0
    rows = errors.v >= top
    region = errors.error_m[rows]
    u, v = np.meshgrid(errors.u, errors.v[rows])
    seen = np.isfinite(region)
    if not seen.any():
        return Coverage(float("nan"), 0.0, limit_m, None, None, reliable_below_row)
    poor = seen & (region > limit_m)
    share = float(poor.sum() / seen.sum())
    if not poor.any():
        return Coverage(
            float(np.median(region[seen])), share, limit_m, None, None, reliable_below_row
        )
    row_range = tuple(float(value) for value in np.percentile(v[poor], [10, 90]))
    column_range = tuple(float(value) for value in np.percentile(u[poor], [10, 90]))
    return Coverage(
        float(np.median(region[seen])),
        share,
        limit_m,
        (row_range[0], row_range[1]),
        (column_range[0], column_range[1]),
        reliable_below_row,
    )
