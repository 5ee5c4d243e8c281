"""Reference images made visible, as in the paper's Fig. 2 and 3.

A 16-bit reference image looks black in an ordinary viewer, and even an 8-bit one is hard
to read. These functions stretch its R and G codes to 8 bits, draw iso-lines of world x and y
(a metric grid) and blend the result over a camera frame. All images are (H, W, 3) uint8 RGB.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.locate import LUTLocator
from cblrs.reference import ReferenceImage

UInt8Image = NDArray[np.uint8]

# Line colours (RGB) of the grid: iso-x lines and iso-y lines.
X_LINE_COLOUR = (255, 255, 255)
Y_LINE_COLOUR = (255, 220, 0)
_PLANE_BLUE = (110, 200, 40, 160, 80, 230)  # B channel per plane index, for visibility


def colourise_reference(reference: ReferenceImage) -> UInt8Image:
    """The reference image made visible.

    R and G codes are stretched to 0..255 whatever the bit depth; B shows which plane a pixel
    sees (a fixed tint per plane); pixels that see no plane are black.

    Args:
        reference: the reference image.

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    pixels = reference.pixels
    max_value = float((1 << reference.bits) - 1)
    image = np.zeros(pixels.shape, dtype=np.uint8)
    scale = 255.0 / max_value
    image[..., 0] = np.rint(pixels[..., 0] * scale).astype(np.uint8)
    image[..., 1] = np.rint(pixels[..., 1] * scale).astype(np.uint8)
    plane_ids = pixels[..., 2]
    for index, plane in enumerate(reference.planes):
        image[..., 2][plane_ids == plane.plane_id] = _PLANE_BLUE[index % len(_PLANE_BLUE)]
    image[plane_ids == 0] = 0
    return image


def reference_world_map(reference: ReferenceImage) -> NDArray[np.float64]:
    """World position of every pixel: (H, W, 2) metres, NaN where no plane is seen."""

    return LUTLocator.from_reference(reference).table.astype(np.float64)


def draw_metric_grid(
    image: UInt8Image,
    reference: ReferenceImage,
    grid_m: float = 1.0,
    labels: bool = True,
    thickness: int | None = None,
    x_colour: tuple[int, int, int] = X_LINE_COLOUR,
    y_colour: tuple[int, int, int] = Y_LINE_COLOUR,
) -> UInt8Image:
    """Draw iso-lines of world x and y every ``grid_m`` metres, labelled, on a copy of ``image``.

    The lines come from the reference image itself (a pixel lies on a line where the grid
    cell of its decoded world position differs from its neighbour's), so they follow lens
    distortion and plane edges exactly as the reference does.

    Args:
        image: (H, W, 3) uint8 RGB image of the reference's size.
        reference: the reference image giving each pixel's world position.
        grid_m: line spacing in metres (> 0).
        labels: write the line values ("x=3", "y=-2") next to the lines.
        thickness: line thickness in pixels; default scales with the image (2 px at 1080p).
        x_colour: RGB colour of lines of constant world x.
        y_colour: RGB colour of lines of constant world y.

    Returns:
        (H, W, 3) uint8 RGB image with the grid drawn.
    """
    if not grid_m > 0:
        raise ValueError(f"grid spacing must be positive, got {grid_m}")
    width, height = reference.image_size
    if image.shape[:2] != (height, width):
        raise ValueError(
            f"image is {image.shape[1]}x{image.shape[0]} but the reference is {width}x{height}"
        )
    output = np.ascontiguousarray(image, dtype=np.uint8).copy()
    if thickness is None:
        thickness = max(1, round(max(width, height) / 960))
    world = reference_world_map(reference)
    plane_ids = reference.pixels[..., 2].astype(np.int64)
    font_scale = max(0.4, min(width, height) / 1080 * 0.8)
    font_thickness = max(1, round(font_scale * 2))
    text_height = cv2.getTextSize("x=0m", cv2.FONT_HERSHEY_SIMPLEX, font_scale, font_thickness)[0][
        1
    ]
    placed: list[tuple[int, int, int, int]] = []
    for axis, colour, prefix in ((0, x_colour, "x"), (1, y_colour, "y")):
        values = world[..., axis]
        with np.errstate(invalid="ignore"):
            cell = np.floor(values / grid_m)
        line = np.zeros((height, width), dtype=bool)
        # A boundary between two horizontally or vertically adjacent pixels of the same plane.
        for first, second, first_id, second_id, target in (
            (cell[:, :-1], cell[:, 1:], plane_ids[:, :-1], plane_ids[:, 1:], line[:, 1:]),
            (cell[:-1, :], cell[1:, :], plane_ids[:-1, :], plane_ids[1:, :], line[1:, :]),
        ):
            with np.errstate(invalid="ignore"):
                target |= (first != second) & (first_id == second_id) & np.isfinite(first)
            target &= np.isfinite(second)
        # Far away the lines crowd into a solid band; leave them out where adjacent lines
        # would be closer than a few line widths.
        spacing = _line_spacing(values, grid_m, reach=4 * thickness)
        with np.errstate(invalid="ignore"):
            line &= ~(spacing < 3 * thickness + 2)
        if thickness > 1:
            kernel = np.ones((thickness, thickness), dtype=np.uint8)
            line = cv2.dilate(line.astype(np.uint8), kernel).astype(bool)
        output[line] = colour
        if labels:
            with np.errstate(invalid="ignore"):
                roomy = line & (spacing >= 1.8 * text_height)
            _label_lines(
                output, values, roomy, grid_m, prefix, colour, placed, font_scale, font_thickness
            )
    return output


def _line_spacing(values: NDArray[np.float64], grid_m: float, reach: int) -> NDArray[np.float64]:
    """Approximate distance in pixels between adjacent iso-lines of ``values``, per pixel.

    Central differences over ``reach`` pixels (wide enough to see through the quantisation
    steps of an 8-bit reference); NaN near plane edges.
    """
    gradient_x = np.full(values.shape, np.nan)
    gradient_y = np.full(values.shape, np.nan)
    gradient_x[:, reach:-reach] = (values[:, 2 * reach :] - values[:, : -2 * reach]) / (2 * reach)
    gradient_y[reach:-reach, :] = (values[2 * reach :, :] - values[: -2 * reach, :]) / (2 * reach)
    with np.errstate(divide="ignore", invalid="ignore"):
        return grid_m / np.hypot(gradient_x, gradient_y)


def _label_lines(
    image: UInt8Image,
    values: NDArray[np.float64],
    line: NDArray[np.bool_],
    grid_m: float,
    prefix: str,
    colour: tuple[int, int, int],
    placed: list[tuple[int, int, int, int]],
    font_scale: float,
    font_thickness: int,
) -> None:
    """Put a label on each iso-line (``line`` marks where labels may go), near the image
    centre, avoiding labels placed before."""
    height, width = line.shape
    rows, columns = np.nonzero(line)
    if len(rows) == 0:
        return
    # The line value: the world coordinate on the line rounded to the nearest grid multiple.
    with np.errstate(invalid="ignore"):
        line_values = np.rint(values[rows, columns] / grid_m)
    finite = np.isfinite(line_values)
    rows, columns, line_values = rows[finite], columns[finite], line_values[finite]
    margin = max(4, round(6 * font_scale))
    centre = np.array([width / 2.0, height / 2.0])
    for value in np.unique(line_values):
        on_line = line_values == value
        line_rows, line_columns = rows[on_line], columns[on_line]
        if len(line_rows) < 20:  # too short to be worth a label
            continue
        text = f"{prefix}={_format_metres(value * grid_m)}"
        (text_width, text_height), baseline = cv2.getTextSize(
            text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, font_thickness
        )
        distance = np.hypot(line_columns - centre[0], line_rows - centre[1])
        for index in np.argsort(distance)[:: max(1, len(distance) // 60)]:
            left = int(line_columns[index]) + 3
            bottom = int(line_rows[index]) - 3
            box = (
                left - margin,
                bottom - text_height - margin,
                left + text_width + margin,
                bottom + baseline + margin,
            )
            if box[0] < 0 or box[1] < 0 or box[2] >= width or box[3] >= height:
                continue
            if any(_overlap(box, other) for other in placed):
                continue
            placed.append(box)
            cv2.putText(
                image,
                text,
                (left, bottom),
                cv2.FONT_HERSHEY_SIMPLEX,
                font_scale,
                (0, 0, 0),
                font_thickness + 2,
                cv2.LINE_AA,
            )
            cv2.putText(
                image,
                text,
                (left, bottom),
                cv2.FONT_HERSHEY_SIMPLEX,
                font_scale,
                colour,
                font_thickness,
                cv2.LINE_AA,
            )
            break


def _overlap(first: tuple[int, int, int, int], second: tuple[int, int, int, int]) -> bool:
    return not (
        first[2] < second[0] or second[2] < first[0] or first[3] < second[1] or second[3] < first[1]
    )


def _format_metres(value: float) -> str:
    if math.isclose(value, round(value), abs_tol=1e-9):
        return f"{round(value)}m"
    return f"{value:g}m"


def reference_overlay(
    reference: ReferenceImage,
    frame: UInt8Image | None = None,
    grid_m: float | None = 1.0,
    alpha: float | None = None,
    labels: bool = True,
) -> UInt8Image:
    """The reference blended over a frame (or a blank canvas) with a labelled metric grid.

    Args:
        reference: the reference image.
        frame: (H, W, 3) uint8 RGB camera frame of the reference's size, or None for a black
            canvas.
        grid_m: grid spacing in metres; None or 0 draws no grid.
        alpha: weight of the reference colours where a plane is seen; default 0.45 over a
            frame and 1.0 on a blank canvas.
        labels: label the grid lines.

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    width, height = reference.image_size
    colours = colourise_reference(reference)
    if frame is None:
        base = np.zeros((height, width, 3), dtype=np.uint8)
        alpha = 1.0 if alpha is None else alpha
    else:
        base = np.asarray(frame)
        if base.ndim == 2:
            base = np.repeat(base[..., None], 3, axis=2)
        if base.shape[:2] != (height, width) or base.shape[2] != 3:
            raise ValueError(
                f"frame is {base.shape[1]}x{base.shape[0]} but the reference is {width}x{height}"
            )
        base = base.astype(np.uint8)
        alpha = 0.45 if alpha is None else alpha
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be within 0..1, got {alpha}")
    seen = reference.pixels[..., 2] != 0
    blended = cv2.addWeighted(base, 1.0 - alpha, colours, alpha, 0.0)
    output = np.where(seen[..., None], blended, base)
    if grid_m:
        output = draw_metric_grid(output, reference, grid_m, labels=labels)
    return output
