"""Recovering the pseudo transform: what an adversary with the database and the site can do.

Pure functions, no I/O; ``cblrs experiment pseudo`` (:mod:`cblrs.experiments.pseudo`) runs
them on WILDTRACK. Two kinds of knowledge are modelled; both assume the adversary knows how
cblrs works (a rotation and a translation, no reflection, no scale):

* **landmarks** — ``k`` points whose site position and pseudo position the adversary pairs
  up (a person seen at a known spot at a known time, a camera mast whose pseudo position the
  matcher's site file holds), each with some error: :func:`fit_rigid` (least squares,
  Kabsch without scale);
* **the walkways** — where people walk on the site (a density of positions over the site
  from an earlier survey, or only the walkable area as a yes/no map): :func:`align_to_density`
  turns the database's pseudo positions through every angle (1 degree, then 0.1 degree
  around the best), finds the translation that puts them where the map says people are (a
  cross-correlation of the rasterised positions with the map's log-density, by FFT) and
  keeps the best angle, then refines angle and translation continuously (Nelder-Mead on the
  interpolated log-density).

:func:`recovery_error` says how far the recovered transform puts each database position from
where the key puts it, in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

# SciPy (ndimage, optimize, signal: about 1.5 CPU-s to import) is imported by the functions
# that use it, so that importing this module costs nothing until an attack runs.

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Rigid:
    """A recovered transform ``site = rotation @ pseudo + translation`` (pseudo -> site).

    Attributes:
        rotation: (2, 2) orthogonal matrix.
        translation: (2,) metres.
    """

    rotation: FloatArray
    translation: FloatArray

    def apply(self, pseudo_xy: ArrayLike) -> FloatArray:
        """Pseudo points (N, 2) -> the site points this transform gives."""
        return np.asarray(pseudo_xy, np.float64) @ self.rotation.T + self.translation


def rotation_matrix(angle_rad: float) -> FloatArray:
    """(2, 2) rotation by ``angle_rad`` counter-clockwise."""
    cosine, sine = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[cosine, -sine], [sine, cosine]])


def fit_rigid(pseudo_xy: ArrayLike, site_xy: ArrayLike, reflection: bool = False) -> Rigid:
    """The rotation and translation that best map ``pseudo_xy`` onto ``site_xy`` (least
    squares; Kabsch without scale).

    Args:
        pseudo_xy: (K, 2) the landmarks' pseudo positions, metres, K >= 2.
        site_xy: (K, 2) the same landmarks' site positions.
        reflection: also allow a reflection (for a scheme that would use one).
    """
    source = np.asarray(pseudo_xy, np.float64)
    target = np.asarray(site_xy, np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 2 \
            or len(source) < 2:
        raise ValueError(f"need two (K, 2) arrays with K >= 2, got {source.shape} and "
                         f"{target.shape}")
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - target_mean).T @ (source - source_mean)
    left, _, right = np.linalg.svd(covariance)
    correction = np.eye(2)
    if not reflection and np.linalg.det(left @ right) < 0:
        correction[1, 1] = -1.0
    rotation = left @ correction @ right
    return Rigid(rotation, target_mean - rotation @ source_mean)


@dataclass(frozen=True)
class DensityMap:
    """What the adversary knows of where people walk: a grid over the site.

    Attributes:
        values: (rows, columns) non-negative weights (a density, or 1/0 for walkable or not);
            row 0 at ``origin``'s y.
        origin: (x, y) metres of the grid's lower-left corner.
        cell_m: cell side, metres.
    """

    values: FloatArray
    origin: tuple[float, float]
    cell_m: float

    @classmethod
    def from_points(
        cls, site_xy: ArrayLike, cell_m: float = 0.25, margin_m: float = 2.0,
        walkable_only: bool = False, smooth_cells: float = 1.0,
    ) -> DensityMap:
        """A map from positions the adversary observed on the site (a survey).

        Args:
            site_xy: (N, 2) metres.
            cell_m: cell side.
            margin_m: empty border around the points.
            walkable_only: keep only "someone walked here" (1/0), not how often.
            smooth_cells: Gaussian blur, in cells, before ``walkable_only`` thresholds it.
        """
        points = np.asarray(site_xy, np.float64)
        points = points[np.isfinite(points).all(axis=1)]
        low = points.min(axis=0) - margin_m
        high = points.max(axis=0) + margin_m
        shape = np.ceil((high - low) / cell_m).astype(int)
        values = _histogram(points - low, cell_m, (int(shape[1]), int(shape[0])))
        if smooth_cells > 0:
            values = _blur(values, smooth_cells)
        if walkable_only:
            values = (values > 1e-3 * values.max()).astype(np.float64)
        return cls(values, (float(low[0]), float(low[1])), cell_m)


def align_to_density(
    pseudo_xy: ArrayLike, density: DensityMap, coarse_deg: float = 1.0,
    fine_deg: float = 0.1,
) -> tuple[Rigid, float]:
    """The rotation and translation that put the pseudo positions where people walk.

    Args:
        pseudo_xy: (N, 2) the database's positions, pseudo metres.
        density: the adversary's map of the site.
        coarse_deg, fine_deg: angle steps of the search (the fine one within one coarse
            step of the best coarse angle).

    Returns:
        ``(transform, score)``: pseudo -> site, and the mean log-density of the positions
        under it (higher is a better fit).
    """
    points = np.asarray(pseudo_xy, np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    centroid = points.mean(axis=0)
    centred = points - centroid
    # The adversary's score is the positions' log-likelihood under the map; empty cells get a
    # small floor so that a few stray positions do not veto an otherwise right angle.
    floor = 1e-3 * float(density.values.max()) if density.values.max() > 0 else 1.0
    log_density = np.log(density.values + floor)
    best: tuple[float, float, FloatArray] | None = None
    angles = np.arange(0.0, 360.0, coarse_deg)
    for angle in angles:
        best = _better(best, _place(centred, angle, density, log_density))
    assert best is not None
    coarse = best[1]
    for angle in np.arange(coarse - coarse_deg, coarse + coarse_deg + 1e-9, fine_deg):
        best = _better(best, _place(centred, float(angle), density, log_density))
    _, angle, offset = best
    from scipy.ndimage import map_coordinates  # lazy, see the imports
    from scipy.optimize import minimize

    # Last, a continuous refinement of angle and offset (the grid search is one cell coarse):
    # the positions' log-density, interpolated between cell centres, by Nelder-Mead.
    def cost(parameters: FloatArray) -> float:
        turned = centred @ rotation_matrix(math.radians(parameters[0])).T + parameters[1:]
        where = (turned - np.array(density.origin)) / density.cell_m - 0.5
        values = map_coordinates(log_density, [where[:, 1], where[:, 0]], order=1,
                                 mode="nearest")
        return -float(values.sum())

    refined = minimize(cost, np.array([angle, *offset]), method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-6, "initial_simplex": np.array(
                           [[angle, *offset], [angle + fine_deg, *offset],
                            [angle, offset[0] + density.cell_m, offset[1]],
                            [angle, offset[0], offset[1] + density.cell_m]])})
    angle, offset = float(refined.x[0]), np.asarray(refined.x[1:], np.float64)
    rotation = rotation_matrix(math.radians(angle))
    return Rigid(rotation, offset - rotation @ centroid), -float(refined.fun) / len(points)


def recovery_error(recovered: Rigid, pseudo_xy: ArrayLike, site_xy: ArrayLike) -> FloatArray:
    """(N,) metres between where ``recovered`` and the key put each position."""
    return np.linalg.norm(recovered.apply(pseudo_xy) - np.asarray(site_xy, np.float64), axis=1)


# ---------------------------------------------------------------------------- helpers


def _better(
    best: tuple[float, float, FloatArray] | None, candidate: tuple[float, float, FloatArray]
) -> tuple[float, float, FloatArray]:
    return candidate if best is None or candidate[0] > best[0] else best


def _place(
    centred: FloatArray, angle_deg: float, density: DensityMap, log_density: FloatArray
) -> tuple[float, float, FloatArray]:
    """Best translation for one angle: (total log-density, angle, site position of the
    centroid)."""
    cell = density.cell_m
    turned = centred @ rotation_matrix(math.radians(angle_deg)).T
    low = turned.min(axis=0)
    extent = np.ceil((turned.max(axis=0) - low) / cell).astype(int) + 1
    counts = _histogram(turned - low, cell, (int(extent[1]), int(extent[0])))
    # score[s] = sum over cells c of counts[c] * log_density[c + s]: a correlation; positions
    # whose grid would leave the map score the floor (the map is padded with it).
    pad_rows, pad_columns = counts.shape
    floor = float(log_density.min())
    padded = np.pad(log_density, ((pad_rows, pad_rows), (pad_columns, pad_columns)),
                    constant_values=floor)
    from scipy.signal import fftconvolve  # lazy, see the imports

    correlation = fftconvolve(padded, counts[::-1, ::-1], mode="valid")
    row, column = np.unravel_index(int(np.argmax(correlation)), correlation.shape)
    # counts' cell (0, 0) lands on padded cell (row, column) = map cell (row - pad_rows, ...)
    corner = np.array(density.origin) + cell * np.array(
        [column - pad_columns, row - pad_rows], dtype=np.float64)
    centroid_site = corner - low
    return float(correlation[row, column]), float(angle_deg), centroid_site


def _histogram(points: FloatArray, cell_m: float, shape: tuple[int, int]) -> FloatArray:
    """Counts of points (metres from the grid corner) per cell, (rows, columns)."""
    columns = np.clip((points[:, 0] / cell_m).astype(int), 0, shape[1] - 1)
    rows = np.clip((points[:, 1] / cell_m).astype(int), 0, shape[0] - 1)
    counts = np.zeros(shape)
    np.add.at(counts, (rows, columns), 1.0)
    return counts


def _blur(values: FloatArray, sigma_cells: float) -> FloatArray:
    radius = max(1, math.ceil(3 * sigma_cells))
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (offsets / sigma_cells) ** 2)
    kernel /= kernel.sum()
    from scipy.signal import fftconvolve  # lazy, see the imports

    return np.asarray(fftconvolve(values, np.outer(kernel, kernel), mode="same").clip(0.0))
