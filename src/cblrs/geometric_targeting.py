"""Geometry-aware targeting: pick the pixel above an object's footprint centre.

A fixed targeting position (bottom centre, or a VTP) ignores what the camera knows: its pose
and lens. Given a class size prior (length, width, height in metres), the detection box is
explained as the image of a 3D box of that size standing on the ground. The ground position
``(x, y)`` and heading ``yaw`` whose projected box best matches the four box edges (weighted
least squares, Levenberg-Marquardt from a few yaw starts, vectorised over all detections) give
the footprint centre; projecting it back to the image gives the target pixel. The camera then
reads and sends the reference colour at that pixel as before, so nothing changes on the wire.

Box edges on the image border are cut by the image and carry no information; they get zero
weight. Such a box leaves fewer edges than unknowns, so its fit is ambiguous (tens of
centimetres off for a car cut by the bottom of the image). Detections of classes without a
size prior, or whose fit fails, fall back to the fixed per-class targeting of
:mod:`cblrs.targeting`.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.datasets.synthetic import (
    CLASS_SIZE_PRIORS,
    clip_boxes,
    project_boxes_3d_unclipped,
)
from cblrs.detections import CLASS_NAMES, Detections
from cblrs.errors import CalibrationError
from cblrs.targeting import target_pixels, targeting_for

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

DEFAULT_CLASS_SIZES: dict[str, tuple[float, float, float]] = dict(CLASS_SIZE_PRIORS)
"""Length (along the heading), width, height in metres per class: the synthetic world's priors."""

_BORDER_PX = 1.0  # box edges this close to the image border are treated as cut by it
_STEP_M = 1e-3  # finite-difference steps
_STEP_RAD = 1e-3


class GeometricTargeter:
    """Target pixels from the camera's calibration and a per-class size prior.

    Args:
        camera: a posed camera (K, R, t; lens distortion is honoured).
        class_sizes: class name -> (length, width, height) metres; missing classes fall back
            to fixed targeting. Default: :data:`DEFAULT_CLASS_SIZES`.
        yaw_starts: number of initial headings in [0, 180) degrees per detection (square
            footprints use two).
        iterations: Levenberg-Marquardt iterations.
        size_sigma: relative spread of real object sizes around the prior; the fit also
            estimates one size scale per object, pulled towards 1 with this spread (0 fixes
            the size to the prior).
        edge_sigma: expected error of a box edge as a fraction of the box size; it weighs
            the size prior against the box edges.
        width_free: classes whose box width is not explained by the size prior (people's
            boxes include arms and stride); only the horizontal centre of their boxes is
            fitted, with top and bottom.

    Example:
        >>> camera = Camera.from_pose("c", (0, 0, 8), 0, 30, 1200, (1920, 1080))
        >>> targeter = GeometricTargeter(camera)
        >>> world_xy, yaw, ok = targeter.fit([[900.0, 500.0, 1100.0, 650.0]], [(4.5, 1.8, 1.5)])
        >>> bool(ok[0])
        True
    """

    def __init__(
        self,
        camera: Camera,
        class_sizes: Mapping[str, tuple[float, float, float]] | None = None,
        yaw_starts: int = 6,
        iterations: int = 8,
        size_sigma: float = 0.1,
        edge_sigma: float = 0.02,
        width_free: Collection[str] = (),
    ):
        if not camera.has_pose:
            raise CalibrationError(
                f"geometric targeting needs a posed camera (K, R, t); {camera.name!r} is "
                "known only by a homography."
            )
        self.camera = camera
        self.class_sizes = dict(DEFAULT_CLASS_SIZES if class_sizes is None else class_sizes)
        for name, size in self.class_sizes.items():
            if len(size) != 3 or min(size) < 0 or max(size) <= 0:
                raise ValueError(f"class size of {name!r} must be (length, width, height) >= 0")
        if size_sigma < 0 or edge_sigma <= 0:
            raise ValueError("size_sigma must be >= 0 and edge_sigma > 0")
        self.yaw_starts = int(yaw_starts)
        self.iterations = int(iterations)
        self.size_sigma = float(size_sigma)
        self.edge_sigma = float(edge_sigma)
        self.width_free = frozenset(width_free)

    # ------------------------------------------------------------------ public API
    def target_pixels(self, detections: Detections) -> tuple[FloatArray, BoolArray]:
        """Target pixels of one camera frame's detections.

        Args:
            detections: boxes with class ids (index into :data:`CLASS_NAMES`).

        Returns:
            ``(pixels, inside)``: (N, 2) float64 pixel coordinates and (N,) bool, False when
            the target is not inside the image (its colour cannot be read) or the box is
            invalid. Rows without a size prior or a converged fit use the class's fixed
            targeting position.
        """
        xyxy = np.asarray(detections.xyxy, dtype=np.float64)
        count = len(xyxy)
        names = [
            CLASS_NAMES[value] if 0 <= value < len(CLASS_NAMES) else "unknown"
            for value in np.asarray(detections.class_id)
        ]
        horizontal = np.array([targeting_for(name).horizontal for name in names])
        vertical = np.array([targeting_for(name).vertical for name in names])
        pixels, inside = target_pixels(
            xyxy.reshape(count, 4), horizontal, vertical, image_size=self.camera.image_size
        )
        known = np.array([name in self.class_sizes for name in names], dtype=bool)
        if not known.any():
            return pixels, inside
        sizes = np.array(
            [self.class_sizes[name] for name, ok in zip(names, known, strict=True) if ok]
        )
        width_free = np.array([name in self.width_free for name in names])[known]
        rows = np.flatnonzero(known)
        geometric, geometric_inside = self.pixels_for(xyxy[rows], sizes, width_free)
        use = np.isfinite(geometric).all(axis=1)
        pixels[rows[use]] = geometric[use]
        inside[rows[use]] = geometric_inside[use]
        return pixels, inside

    def pixels_for(
        self, xyxy: NDArray, size_lwh: NDArray, width_free: NDArray | bool = False
    ) -> tuple[FloatArray, BoolArray]:
        """Target pixels of boxes with known 3D sizes.

        Args:
            xyxy: (N, 4) pixel boxes.
            size_lwh: (N, 3) or (3,) object sizes in metres.
            width_free: (N,) or scalar bool, True to fit only the horizontal box centre.

        Returns:
            ``(pixels, inside)``: (N, 2) raw pixels of the fitted footprint centres (NaN where
            the fit failed) and (N,) bool, True when that pixel lies in the image.
        """
        world_xy, _, ok = self.fit(xyxy, size_lwh, width_free)
        pixels = np.full((len(world_xy), 2), np.nan)
        if ok.any():
            projected, valid = self.camera.world_to_pixel(world_xy[ok])
            projected[~valid] = np.nan
            pixels[ok] = projected
        finite = np.isfinite(pixels).all(axis=1)
        inside = finite & self.camera.contains(np.where(finite[:, None], pixels, -1.0))
        return pixels, inside

    def fit(
        self, xyxy: NDArray, size_lwh: NDArray, width_free: NDArray | bool = False
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Ground position and heading whose projected 3D box best explains each box.

        Args:
            xyxy: (N, 4) pixel boxes (x_min, y_min, x_max, y_max).
            size_lwh: (N, 3) or (3,) length, width, height in metres.
            width_free: (N,) or scalar bool, True to fit only the horizontal box centre.

        Returns:
            ``(world_xy, yaw_deg, ok)``: (N, 2) footprint centres in metres, (N,) headings in
            degrees within [0, 180), and (N,) bool, False where the box is invalid or no fit
            converged (those rows are NaN).
        """
        boxes = np.asarray(xyxy, dtype=np.float64)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"xyxy must have shape (N, 4), got {boxes.shape}")
        count = len(boxes)
        sizes = np.broadcast_to(np.asarray(size_lwh, dtype=np.float64), (count, 3)).copy()
        free_width: NDArray[np.bool_] = np.broadcast_to(
            np.asarray(width_free, dtype=bool), (count,)
        ).copy()
        world_xy = np.full((count, 2), np.nan)
        yaw_deg = np.full(count, np.nan)
        with np.errstate(invalid="ignore"):
            usable = (
                np.isfinite(boxes).all(axis=1)
                & (boxes[:, 2] > boxes[:, 0])
                & (boxes[:, 3] > boxes[:, 1])
            )
        if not usable.any():
            return world_xy, yaw_deg, usable
        rows = np.flatnonzero(usable)
        position, heading, cost = self._solve(boxes[rows], sizes[rows], free_width[rows])
        ok = np.isfinite(position).all(axis=1) & np.isfinite(cost)
        world_xy[rows[ok]] = position[ok]
        yaw_deg[rows[ok]] = np.degrees(heading[ok]) % 180.0
        converged = np.zeros(count, dtype=bool)
        converged[rows[ok]] = True
        return world_xy, yaw_deg, converged

    # ------------------------------------------------------------------ solver
    def _initial_positions(self, boxes: FloatArray, sizes: FloatArray) -> FloatArray:
        """Ground guess: the box centre's ray met at half the object's height."""
        centre = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2])
        guess = np.full((len(boxes), 2), np.nan)
        for half_height in np.unique(sizes[:, 2] / 2.0):
            rows = sizes[:, 2] / 2.0 == half_height
            if half_height < self.camera.centre[2]:
                guess[rows], _ = self.camera.pixel_to_world(centre[rows], height_m=half_height)
        missing = ~np.isfinite(guess).all(axis=1)
        if missing.any():
            bottom = np.column_stack([centre[missing, 0], boxes[missing, 3]])
            guess[missing], _ = self.camera.pixel_to_world(bottom)
        return guess

    def _predict(self, parameters: FloatArray, sizes: FloatArray) -> FloatArray:
        """(M, 4) image boxes at (x, y, yaw radians, log size scale), clipped to the image."""
        xyxy, _ = project_boxes_3d_unclipped(
            self.camera,
            parameters[:, :2],
            sizes * np.exp(parameters[:, 3:4]),
            np.degrees(parameters[:, 2]),
        )
        clipped, _ = clip_boxes(xyxy, self.camera.image_size)
        return clipped

    def _solve(
        self, boxes: FloatArray, sizes: FloatArray, width_free: NDArray[np.bool_]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        count = len(boxes)
        width, height = self.camera.image_size
        weights = np.ones((count, 4))
        weights[:, 0] = boxes[:, 0] > -0.5 + _BORDER_PX
        weights[:, 1] = boxes[:, 1] > -0.5 + _BORDER_PX
        weights[:, 2] = boxes[:, 2] < width - 0.5 - _BORDER_PX
        weights[:, 3] = boxes[:, 3] < height - 0.5 - _BORDER_PX
        # Residuals in units of the box's size, so that the damping works alike for near
        # and far objects.
        scale = np.maximum(boxes[:, 3] - boxes[:, 1], boxes[:, 2] - boxes[:, 0])[:, None]
        # Residuals are edges @ mix: one row per edge, one column per residual.
        mix = np.zeros((count, 4, 4))
        mix[:, np.arange(4), np.arange(4)] = weights / np.maximum(scale, 1.0)
        # Width-free rows with both sides in view fit the centre (x_min + x_max) / sqrt(2),
        # which has the noise of one edge.
        centre_only = width_free & (weights[:, 0] > 0) & (weights[:, 2] > 0)
        mix[centre_only, 0, 0] = mix[centre_only, 2, 0] = 1.0 / np.sqrt(2) / scale[centre_only, 0]
        mix[centre_only, 2, 2] = 0.0

        guess = self._initial_positions(boxes, sizes)
        square: NDArray[np.bool_] = np.isclose(sizes[:, 0], sizes[:, 1], rtol=0.15)
        starts = np.linspace(0.0, np.pi, self.yaw_starts, endpoint=False)
        # Every detection tries every start; square footprints need only two of them, but a
        # uniform layout keeps the arrays rectangular (their extra starts are cheap).
        hypotheses = len(starts)
        parameters = np.zeros((count, hypotheses, 4))
        parameters[:, :, :2] = guess[:, None, :]
        parameters[:, :, 2] = starts[None, :]
        active = np.all(np.isfinite(guess), axis=1, keepdims=True)
        active_hypotheses = np.repeat(active, hypotheses, axis=1)
        active_hypotheses[square, 2:] = False
        flat_parameters = parameters.reshape(-1, 4)
        flat_boxes = np.repeat(boxes, hypotheses, axis=0)
        flat_sizes = np.repeat(sizes, hypotheses, axis=0)
        flat_mix = np.repeat(mix, hypotheses, axis=0)
        selected = active_hypotheses.ravel()
        cost = np.full(count * hypotheses, np.inf)
        if selected.any():
            # First with the size fixed to the prior (well determined even for boxes cut by
            # the image border), then with the size scale free from there.
            arguments = (flat_boxes[selected], flat_sizes[selected], flat_mix[selected])
            fitted, fitted_cost = self._levenberg_marquardt(
                flat_parameters[selected], *arguments, free=3, iterations=self.iterations
            )
            if self.size_sigma > 0:
                fitted, fitted_cost = self._levenberg_marquardt(
                    fitted, *arguments, free=4, iterations=max(self.iterations // 2, 1)
                )
            flat_parameters[selected] = fitted
            cost[selected] = fitted_cost
        costs = cost.reshape(count, hypotheses)
        best = np.argmin(costs, axis=1)
        chosen = flat_parameters.reshape(count, hypotheses, 4)[np.arange(count), best]
        best_cost = costs[np.arange(count), best]
        chosen[~np.isfinite(best_cost)] = np.nan
        return chosen[:, :2], chosen[:, 2], best_cost

    def _levenberg_marquardt(
        self,
        parameters: FloatArray,
        boxes: FloatArray,
        sizes: FloatArray,
        mix: FloatArray,
        free: int,
        iterations: int,
    ) -> tuple[FloatArray, FloatArray]:
        """Damped Gauss-Newton on the first ``free`` parameters (x, y, yaw[, log scale])."""
        steps = np.array([_STEP_M, _STEP_M, _STEP_RAD, _STEP_RAD])[:free]
        # The size prior enters as a fifth residual, in the units of the (normalised) edges.
        prior_weight = self.edge_sigma / self.size_sigma if self.size_sigma > 0 else 0.0

        count = len(parameters)
        blocks = free + 1
        tiled_sizes = np.tile(sizes, (blocks, 1))
        tiled_boxes = np.tile(boxes, (blocks, 1))
        tiled_mix = np.tile(mix, (blocks, 1, 1))

        def evaluate(values: FloatArray) -> tuple[FloatArray, FloatArray]:
            """Residuals (M, 5) and forward-difference Jacobian (M, 5, free) in one projection."""
            stacked = np.tile(values, (blocks, 1))
            for column in range(free):
                stacked[(column + 1) * count : (column + 2) * count, column] += steps[column]
            predicted = self._predict(stacked, tiled_sizes)
            edges = np.einsum("mk,mkj->mj", predicted - tiled_boxes, tiled_mix)
            residual = np.column_stack([edges, prior_weight * stacked[:, 3]])
            base = residual[:count]
            shifted = residual[count:].reshape(free, count, 5)
            jacobian = np.moveaxis((shifted - base) / steps[:, None, None], 0, 2)
            return base, np.nan_to_num(jacobian, nan=0.0, posinf=0.0, neginf=0.0)

        current, jacobian = evaluate(parameters)
        cost = np.sum(current**2, axis=1)
        cost[~np.isfinite(cost)] = np.inf
        damping = np.full(count, 1e-3)
        for _ in range(iterations):
            normal = np.einsum("mki,mkj->mij", jacobian, jacobian)
            gradient = np.einsum("mki,mk->mi", jacobian, np.nan_to_num(current))
            diagonal = np.einsum("mii->mi", normal)
            regularised = normal + (damping[:, None] * diagonal + 1e-9)[:, :, None] * np.eye(free)
            try:
                delta = -np.linalg.solve(regularised, gradient[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:
                break
            # Do not let one step move the object further than its own length.
            limit = np.maximum(sizes[:, 0], 0.5)[:, None]
            delta[:, :2] = np.clip(delta[:, :2], -limit, limit)
            delta[:, 2:] = np.clip(delta[:, 2:], -0.5, 0.5)
            candidate = parameters.copy()
            candidate[:, :free] += delta
            candidate_residuals, candidate_jacobian = evaluate(candidate)
            candidate_cost = np.sum(candidate_residuals**2, axis=1)
            candidate_cost[~np.isfinite(candidate_cost)] = np.inf
            better = candidate_cost < cost
            parameters = np.where(better[:, None], candidate, parameters)
            current = np.where(better[:, None], candidate_residuals, current)
            jacobian = np.where(better[:, None, None], candidate_jacobian, jacobian)
            cost = np.where(better, candidate_cost, cost)
            damping = np.where(better, damping * 0.3, damping * 10.0)
        return parameters, cost
