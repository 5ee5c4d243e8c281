"""The picture of a calibration from clicked points: is it right?

The camera's frame (or a grey canvas of its size) with the fitted camera's metric ground
grid, every clicked point (circle; orange when left out as an outlier) and where the fit puts
its world point (cross, joined to the click by a line), labelled with both errors, and a box
summing up the model, the errors, the focal length and the camera's position. The part of
the image whose predicted ground error exceeds half a metre
(:mod:`cblrs.calibrate.uncertainty`) is shaded red: click more points there.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference
from cblrs.viz.reference import draw_metric_grid

UInt8Image = NDArray[np.uint8]

_CLICK = (40, 220, 60)
_OUTLIER = (255, 150, 0)
_PROJECTED = (235, 40, 40)
_POOR = np.array([220, 30, 30], dtype=np.float32)
_GRID_STEPS_M = (0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)


def grid_step(world_xy: NDArray, lines: int = 12) -> float:
    """A round grid spacing (metres) giving about ``lines`` lines over the points' extent."""
    extent = float(np.ptp(world_xy, axis=0).max()) if len(world_xy) else 10.0
    for step in _GRID_STEPS_M:
        if extent / step <= lines:
            return step
    return _GRID_STEPS_M[-1]


def calibration_picture(
    fit: Any, frame: UInt8Image | None = None, grid_m: float | None = None
) -> UInt8Image:
    """Draw a :class:`cblrs.calibrate.CalibrationFit`.

    Args:
        fit: the calibration.
        frame: (H, W, 3) uint8 RGB frame of the camera, or None for a grey canvas.
        grid_m: grid spacing in metres (default: about 12 lines over the points).

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    camera = fit.camera
    width, height = camera.image_size
    if frame is None:
        image = np.full((height, width, 3), 96, dtype=np.uint8)
    else:
        if frame.shape[:2] != (height, width):
            raise ValueError(
                f"the frame is {frame.shape[1]}x{frame.shape[0]} but the camera is {width}x{height}"
            )
        # Dim the frame a little so the drawing stands out.
        image = (np.asarray(frame, dtype=np.float32) * 0.75).astype(np.uint8)
    world = fit.points.world_xy
    step = grid_m or grid_step(world)
    low = world.min(axis=0) - max(3 * step, 0.5 * float(np.ptp(world, axis=0).max()))
    high = world.max(axis=0) + max(3 * step, 0.5 * float(np.ptp(world, axis=0).max()))
    plane = PlaneSpec(
        1, (float(low[0]), float(low[1])), float(high[0] - low[0]), float(high[1] - low[1]), bits=16
    )
    reference = render_reference(camera, plane)
    image = draw_metric_grid(image, reference, grid_m=step)
    coverage = getattr(fit, "coverage", None)
    errors = getattr(fit, "error_map", None)
    if errors is not None and coverage is not None:
        poor = errors.full((width, height)) > coverage.limit_m
        shaded = image[poor].astype(np.float32) * 0.6 + _POOR * 0.4
        image[poor] = shaded.astype(np.uint8)
    scale = max(width, height) / 1920
    radius = max(4, round(9 * scale))
    thickness = max(1, round(2 * scale))
    font_scale = max(0.4, 0.6 * scale)
    projected, in_front = camera.world_to_pixel(world)
    for index, name in enumerate(fit.points.names):
        click = fit.points.image_xy[index]
        colour = _CLICK if fit.inliers[index] else _OUTLIER
        centre = (round(click[0]), round(click[1]))
        if in_front[index] and np.all(np.isfinite(projected[index])):
            target = (round(projected[index][0]), round(projected[index][1]))
            if abs(target[0]) < 10 * width and abs(target[1]) < 10 * height:
                cv2.line(image, centre, target, _PROJECTED, thickness, cv2.LINE_AA)
                size = radius
                cv2.line(
                    image,
                    (target[0] - size, target[1] - size),
                    (target[0] + size, target[1] + size),
                    _PROJECTED,
                    thickness,
                    cv2.LINE_AA,
                )
                cv2.line(
                    image,
                    (target[0] - size, target[1] + size),
                    (target[0] + size, target[1] - size),
                    _PROJECTED,
                    thickness,
                    cv2.LINE_AA,
                )
        cv2.circle(image, centre, radius, colour, thickness, cv2.LINE_AA)
        error_m = fit.error_m[index]
        label = f"{name}: {fit.error_px[index]:.1f} px" + (
            f", {error_m:.2f} m" if math.isfinite(error_m) else ""
        )
        if not fit.inliers[index]:
            label += " (outlier)"
        _text(image, label, (centre[0] + radius + 3, centre[1] - radius), colour, font_scale)
    for row, line in enumerate(summary_lines(fit)):
        _text(
            image,
            line,
            (8, 8 + row * int(34 * font_scale + 10)),
            (255, 255, 255),
            font_scale,
            background=True,
        )
    legend = "circle: clicked   x: world point projected by the fit   grid: fitted ground, " + (
        f"{step:g} m"
    )
    if coverage is not None:
        legend += f"   red: predicted error > {coverage.limit_m:g} m"
    _text(
        image,
        legend,
        (8, height - int(34 * font_scale + 12)),
        (255, 255, 255),
        font_scale,
        background=True,
    )
    return image


def summary_lines(fit: Any) -> list[str]:
    """The few lines of text that sum up a fit."""
    inliers = fit.inliers
    lines = [
        f"{fit.camera.name}: model {fit.model.value}, {int(inliers.sum())}/{len(inliers)} points",
        f"error: RMS {fit.rms_px:.1f} px, median {np.nanmedian(fit.error_m[inliers]):.3f} m, "
        f"max {np.nanmax(fit.error_m[inliers]):.3f} m",
    ]
    if fit.focal_px is not None:
        lens = f"focal {fit.focal_px:.0f} px"
        if fit.camera.has_distortion:
            lens += f", k1 {fit.camera.distortion[0]:+.3f}"
        lines.append(lens)
    if fit.position is not None:
        x, y, z = fit.position
        lines.append(f"camera at ({x:.2f}, {y:.2f}) m, {z:.2f} m high [{fit.position_source}]")
    else:
        lines.append("camera position unknown")
    held_out = getattr(fit, "held_out", {})
    if held_out:
        scores = ", ".join(
            f"{model} {_held_out_metres(result):.2f} m" for model, result in held_out.items()
        )
        lines.append(f"held-out points (median ground error): {scores}")
    coverage = getattr(fit, "coverage", None)
    if coverage is not None and math.isfinite(coverage.median_m):
        text = f"predicted ground error: median {coverage.median_m:.2f} m below the highest point"
        if coverage.reliable_below_row is not None:
            text += f"; over {coverage.limit_m:g} m above row {coverage.reliable_below_row:.0f}"
        lines.append(text)
    return lines


def _held_out_metres(result: Any) -> float:
    finite = result.error_m[np.isfinite(result.error_m)]
    return float(np.median(finite)) if len(finite) else math.nan


def _text(
    image: UInt8Image,
    text: str,
    origin: tuple[int, int],
    colour: tuple[int, int, int],
    font_scale: float,
    background: bool = True,
) -> None:
    font = cv2.FONT_HERSHEY_SIMPLEX
    thickness = max(1, round(font_scale * 2))
    (text_width, text_height), baseline = cv2.getTextSize(text, font, font_scale, thickness)
    height, width = image.shape[:2]
    x = int(np.clip(origin[0], 0, max(width - text_width - 6, 0)))
    y = int(np.clip(origin[1], 0, max(height - text_height - baseline - 6, 0)))
    if background:
        cv2.rectangle(
            image, (x, y), (x + text_width + 6, y + text_height + baseline + 6), (0, 0, 0), -1
        )
    cv2.putText(
        image, text, (x + 3, y + text_height + 3), font, font_scale, colour, thickness, cv2.LINE_AA
    )
