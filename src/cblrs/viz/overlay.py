"""Per-camera overlays: reference colours, detection boxes and target pixels (the paper's Fig. 3).

Images are (H, W, 3) uint8 RGB; :func:`save_image` writes them as PNG (OpenCV wants BGR,
which it handles).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.detections import CLASS_NAMES, Detections
from cblrs.reference import ReferenceImage
from cblrs.viz.reference import reference_overlay

UInt8Image = NDArray[np.uint8]

# Matplotlib's "tab10" without its grey (grey is for ground truth, unknown ids and
# structures); the same in overlays and trajectory plots, so an id keeps its colour.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
    (23, 190, 207),
)


def id_colour(identity: int) -> tuple[int, int, int]:
    """A stable RGB colour for an identity (negative ids are grey)."""
    if identity < 0:
        return (200, 200, 200)
    # Spread neighbouring ids over the palette (consecutive ids often meet in one scene).
    return PALETTE[(int(identity) * 7 + int(identity) // len(PALETTE)) % len(PALETTE)]


def camera_overlay(
    reference: ReferenceImage,
    detections: Detections,
    target_pixels: NDArray,
    frame: UInt8Image | None = None,
    identities: NDArray | None = None,
    grid_m: float | None = 1.0,
    title: str | None = None,
    highlight_pixels: NDArray | None = None,
    caption: str | None = None,
    overlay_opacity: float = 1.0,
) -> UInt8Image:
    """Reference colours, boxes and target pixels of one camera frame.

    Args:
        reference: the camera's reference image.
        detections: the frame's N boxes (pixels).
        target_pixels: (N, 2) target pixel of each box (NaN rows are skipped).
        frame: (H, W, 3) uint8 RGB camera image to draw on, or None for the reference alone.
        identities: (N,) ids to label and colour the boxes by (e.g. track ids); defaults to
            ``detections.object_id`` (-1 draws unlabelled grey boxes).
        grid_m: metric grid spacing in metres (None: no grid).
        title: text written in the top-left corner.
        highlight_pixels: (M, 2) pixels marked with a green ring, e.g. one world point seen
            by several cameras (the paper's green dot).
        caption: text written in the bottom-left corner (e.g. a legend).
        overlay_opacity: how strongly the reference colours and the grid show over
            ``frame`` (1: as :func:`cblrs.viz.reference.reference_overlay` draws them; less
            lets a real camera image show through).

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    targets = np.asarray(target_pixels, dtype=np.float64).reshape(-1, 2)
    if len(targets) != len(detections):
        raise ValueError(
            f"target_pixels has {len(targets)} rows but there are {len(detections)} detections"
        )
    ids = detections.object_id if identities is None else np.asarray(identities, np.int64)
    if len(ids) != len(detections):
        raise ValueError(f"identities has {len(ids)} rows but there are {len(detections)} boxes")
    image = reference_overlay(reference, frame, grid_m=grid_m, labels=True)
    if frame is not None and overlay_opacity < 1.0:
        if not 0.0 <= overlay_opacity <= 1.0:
            raise ValueError(f"overlay_opacity must be within 0..1, got {overlay_opacity}")
        image = np.asarray(
            cv2.addWeighted(
                np.asarray(frame, np.uint8), 1.0 - overlay_opacity, image, overlay_opacity, 0.0
            ),
            np.uint8,
        )
    image = np.ascontiguousarray(image)
    width, height = reference.image_size
    scale = max(width, height) / 1280.0
    thickness = max(1, round(2 * scale))
    font_scale = 0.55 * scale
    for row in range(len(detections)):
        colour = id_colour(int(ids[row]))
        x0, y0, x1, y1 = (round(value) for value in detections.xyxy[row])
        cv2.rectangle(image, (x0, y0), (x1, y1), (0, 0, 0), thickness + 2, cv2.LINE_8)
        cv2.rectangle(image, (x0, y0), (x1, y1), colour, thickness, cv2.LINE_8)
        class_id = int(detections.class_id[row])
        name = CLASS_NAMES[class_id] if 0 <= class_id < len(CLASS_NAMES) else str(class_id)
        if ids[row] < 0:
            # An unlabelled person box says nothing a label would add; other classes do.
            label = "" if name == "person" else name
        else:
            # People are the common case: the id alone keeps crowded frames readable.
            label = str(int(ids[row])) if name == "person" else f"{name} {int(ids[row])}"
        if label:
            _label(image, label, (x0, y0), colour, font_scale, thickness)
    for row, (x, y) in enumerate(targets):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        centre = (round(x), round(y))
        radius = max(3, round(5 * scale))
        cv2.circle(image, centre, radius + 2, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(image, centre, radius, id_colour(int(ids[row])), -1, cv2.LINE_AA)
        cv2.circle(image, centre, max(1, radius // 3), (255, 255, 255), -1, cv2.LINE_AA)
    if highlight_pixels is not None:
        for x, y in np.asarray(highlight_pixels, dtype=np.float64).reshape(-1, 2):
            if np.isfinite(x) and np.isfinite(y):
                centre = (round(x), round(y))
                cv2.circle(
                    image, centre, round(12 * scale), (0, 255, 0), thickness + 1, cv2.LINE_AA
                )
    if title:
        _label(image, title, (0, 0), (255, 255, 255), font_scale * 1.4, thickness, inside=True)
    if caption:
        _label(image, caption, (0, height), (255, 255, 255), font_scale, thickness)
    return image


def _label(
    image: UInt8Image,
    text: str,
    corner: tuple[int, int],
    colour: tuple[int, int, int],
    font_scale: float,
    thickness: int,
    inside: bool = False,
) -> None:
    """Text on a dark box above ``corner`` (or just inside the image when there is no room)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    text_thickness = max(1, thickness // 2 + 1) if not inside else max(1, thickness)
    (text_width, text_height), baseline = cv2.getTextSize(text, font, font_scale, text_thickness)
    x, y = corner
    pad = 3
    top = y - text_height - baseline - 2 * pad
    if inside or top < 0:
        top = max(y, 0)
    x = int(np.clip(x, 0, max(image.shape[1] - text_width - 2 * pad, 0)))
    bottom = top + text_height + baseline + 2 * pad
    cv2.rectangle(image, (x, top), (x + text_width + 2 * pad, bottom), (0, 0, 0), -1)
    cv2.putText(
        image,
        text,
        (x + pad, bottom - baseline - pad),
        font,
        font_scale,
        colour,
        text_thickness,
        cv2.LINE_AA,
    )


def save_image(path: str | Path, image: UInt8Image) -> Path:
    """Write an (H, W, 3) uint8 RGB image as PNG, readable by its owner only (0600, also
    when the file existed with a wider mode: an overlay holds a camera's frame, which shows
    people); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise OSError(f"could not write image {path}")
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as out:
        os.fchmod(descriptor, 0o600)
        out.write(encoded.tobytes())
    return path


# Faces of a box from cblrs.datasets.synthetic.box_corners_3d (corners 0-3 bottom, 4-7 top).
_FACES = ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
SKY_COLOUR = (196, 214, 230)
GROUND_COLOUR = (112, 116, 112)


def world_frame(camera: Camera, markings: Sequence[Any] = ()) -> UInt8Image:
    """A plain stand-in for a camera image: sky above the horizon, grey ground below.

    Args:
        camera: the camera (its image size and pose).
        markings: ground paint, objects with ``polygon`` ((x, y), ... metres) and ``colour``
            (r, g, b), e.g. :class:`cblrs.datasets.synthetic.GroundMarking`; drawn in order.

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    width, height = camera.image_size
    # The horizon is a line, so rows and columns at a coarse step are enough to find it.
    step = 4
    columns, rows = np.meshgrid(np.arange(0, width, step), np.arange(0, height, step))
    _, valid = camera.pixel_to_world(np.column_stack([columns.ravel(), rows.ravel()]))
    ground = cv2.resize(
        valid.reshape(columns.shape).astype(np.uint8),
        (width, height),
        interpolation=cv2.INTER_NEAREST,
    ).astype(bool)
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[:] = SKY_COLOUR
    image[ground] = GROUND_COLOUR
    for marking in markings:
        polygon = np.asarray(marking.polygon, dtype=np.float64).reshape(-1, 2)
        pixels, valid = camera.world_to_pixel(polygon)
        if len(polygon) < 3 or not valid.all():
            continue  # partly behind the camera: not worth clipping for a picture
        painted = np.zeros((height, width), dtype=np.uint8)
        cv2.fillPoly(painted, [np.round(pixels).astype(np.int32)], 1, cv2.LINE_AA)
        image[(painted > 0) & ground] = marking.colour
    return image


def draw_boxes_3d(
    image: UInt8Image,
    camera: Camera,
    corners: NDArray,
    identities: NDArray | None = None,
    colours: NDArray | None = None,
) -> UInt8Image:
    """Draw solid, shaded 3D boxes (far ones first) on a copy of an image.

    Args:
        image: (H, W, 3) uint8 RGB.
        camera: the posed camera of the image.
        corners: (N, 8, 3) box corners in world metres, as from
            :func:`cblrs.datasets.synthetic.box_corners_3d`.
        identities: (N,) ids that pick each box's colour; default: all grey.
        colours: (N, 3) RGB colours, overriding ``identities``.

    Returns:
        (H, W, 3) uint8 RGB image. Boxes reaching behind the camera are skipped.
    """
    output = np.ascontiguousarray(image.copy())
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 8, 3)
    if len(corners) == 0:
        return output
    ids = np.full(len(corners), -1) if identities is None else np.asarray(identities)
    centre = camera.centre
    depth = camera.to_camera_frame(corners.reshape(-1, 3))[:, 2].reshape(-1, 8)
    light = np.array([0.35, -0.25, 0.9]) / np.linalg.norm([0.35, -0.25, 0.9])
    for index in np.argsort(-depth.mean(axis=1)):
        if (depth[index] <= 0.1).any():
            continue
        box = corners[index]
        pixels, _ = camera.project_points(box)
        if colours is not None:
            base = np.asarray(colours[index], dtype=np.float64)
        else:
            base = np.array(id_colour(int(ids[index])), dtype=np.float64)
        box_centre = box.mean(axis=0)
        for face in _FACES:
            points = box[list(face)]
            face_centre = points.mean(axis=0)
            normal = face_centre - box_centre
            normal /= max(np.linalg.norm(normal), 1e-12)
            if np.dot(normal, centre - face_centre) <= 0:
                continue  # facing away from the camera
            shade = 0.45 + 0.55 * max(float(np.dot(normal, light)), 0.0)
            polygon = np.round(pixels[list(face)]).astype(np.int32)
            cv2.fillConvexPoly(output, polygon, tuple(float(v) for v in base * shade), cv2.LINE_AA)
            cv2.polylines(output, [polygon], True, (30, 30, 30), 1, cv2.LINE_AA)
    return output
