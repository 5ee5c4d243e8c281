"""The camera side of the pipeline: detections -> target pixels -> colours -> message.

This is all an edge camera computes per frame. Its output, a :class:`CameraMessage`, holds
boxes and reference colours only.

Boxes a camera refuses outright (:func:`box_rejections`; dropped from the message and counted
by reason; ``cblrs locate --boxes`` applies the same rule): a coordinate that is not finite
(``not_finite``), ``x_max < x_min`` or ``y_max < y_min`` (``inverted``), and a box that does
not overlap the image at all (``outside_image``: no detector of this camera produced it).

Policy for locations a camera cannot vouch for (colour ``(0, 0, 0)``, "no location"):

* the target pixel lies outside the image (a box cut by the image border at the target's
  side, e.g. the feet of a person below the bottom edge): the clamped pixel would put the
  object nearer the camera than it is, and a wrong location is worse than none when other
  cameras see the object;
* the box is cut by the image border on the target's side (a detector clips boxes to the
  image): a box ending at the bottom row hides where the feet are, so its bottom edge is
  not a ground contact. Vehicles, whose horizontal centre also matters, are dropped when
  cut at either side as well;
* the target pixel sees no plane;
* optionally (``drop_hidden_feet``, for a detector's boxes): the target lies inside the box
  of a nearer object — one whose box reaches lower in the image, so it stands between
  the camera and the target. A detector's box covers only what is visible: the box of a
  person half hidden behind another ends where the visible part ends, not at the feet,
  and its "foot point" would put the person metres too far. Annotated boxes (WILDTRACK,
  MultiviewX) are drawn around the whole person, hidden parts included, so they keep
  their location. A doubtful box (scored below :data:`~cblrs.detections.SURE_CONFIDENCE`)
  counts as the nearer object only for boxes scored lower still: a detector run at a low
  threshold (to let the tracker confirm weak boxes,
  :mod:`cblrs.matching.fusion.low_confidence`) also reports a bag, a shadow or a second
  box around one person, and such a box must not take away the location of a person the
  detector is sure of.

Vehicles are seen from above and the side, so the bottom of their box is the footprint's
edge nearest the camera, not its centre (the paper's Fig. 1). With the default targeting the
camera aims at the bottom edge and moves the located point away from itself along the
ground by half the class's typical footprint depth (:data:`GROUND_DEPTH_OFFSET_M`). The
direction comes from the reference image alone: the ground point of a pixel a little
higher in the box. For people the offset is zero (their feet are the footprint).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from cblrs.arrays import unique_integers
from cblrs.detections import CLASS_NAMES, SURE_CONFIDENCE, CameraMessage, Detections
from cblrs.reference import Reference
from cblrs.targeting import TargetingPosition, target_pixels, targeting_for

# Half the typical footprint depth seen along a viewing ray, metres (a 4.5 x 1.8 m car shows
# between 0.9 and 2.4 m of depth depending on its heading; 1.5 m is the middle).
GROUND_DEPTH_OFFSET_M: dict[str, float] = {
    "car": 1.5,
    "truck": 2.5,
    "bus": 3.0,
    "bicycle": 0.4,
    "motorcycle": 0.5,
}


BOX_REJECTIONS = ("not_finite", "inverted", "outside_image")
"""Why a camera refuses a box (see the module docstring)."""


def box_rejections(xyxy: np.ndarray, image_size: tuple[int, int]) -> list[str | None]:
    """Per box, why a camera refuses it (one of :data:`BOX_REJECTIONS`), or None.

    Args:
        xyxy: (N, 4) boxes, pixels.
        image_size: (width, height) of the camera's image.
    """
    boxes = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    width, height = image_size
    reasons: list[str | None] = []
    with np.errstate(invalid="ignore"):
        finite = np.asarray(np.isfinite(boxes).all(axis=1))
        inverted = (boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1])
        # Pixel areas span -0.5 .. size - 0.5; a box touching that area overlaps the image.
        outside = ((boxes[:, 2] < -0.5) | (boxes[:, 0] > width - 0.5)
                   | (boxes[:, 3] < -0.5) | (boxes[:, 1] > height - 0.5))
    for index in range(len(boxes)):
        if not finite[index]:
            reasons.append("not_finite")
        elif inverted[index]:
            reasons.append("inverted")
        elif outside[index]:
            reasons.append("outside_image")
        else:
            reasons.append(None)
    return reasons


def location_status(
    xyxy: np.ndarray,
    pixels: np.ndarray,
    inside: np.ndarray,
    valid: np.ndarray,
    vertical: np.ndarray,
    sides_matter: np.ndarray,
    image_size: tuple[int, int],
) -> list[str]:
    """Per box, what the camera sends: ``located``, or why not (``target_outside``,
    ``cut_by_border``, ``no_plane``); the same words ``cblrs locate --boxes`` prints."""
    cut = cut_by_border(xyxy, vertical, sides_matter, image_size)
    status = []
    for index in range(len(pixels)):
        if not inside[index]:
            status.append("target_outside")
        elif cut[index]:
            status.append("cut_by_border")
        elif not valid[index]:
            status.append("no_plane")
        else:
            status.append("located")
    return status


class Targeter(Protocol):
    """Chooses target pixels for a frame's detections (see :mod:`cblrs.geometric_targeting`)."""

    def target_pixels(self, detections: Detections) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) target pixels and (N,) bool, True where the target lies in the image."""
        ...


# A box in front must reach lower than the target by more than this share of the target
# box's height: box bottoms of people standing side by side differ by detector noise.
HIDDEN_FEET_TOLERANCE = 0.05

# Targeting used together with the offsets: the bottom edge of the box.
OFFSET_TARGETING = TargetingPosition(0.5, 1.0)
# How far above the target (fraction of the box height, at least 2 px) the second pixel is
# taken to find the away-from-camera direction on the ground.
_DIRECTION_STEP = 0.1


def targeting_columns(
    class_id: np.ndarray, overrides: dict[str, TargetingPosition] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-detection (horizontal, vertical) targeting fractions from class defaults."""
    overrides = overrides or {}
    horizontal = np.empty(len(class_id))
    vertical = np.empty(len(class_id))
    for value in unique_integers(class_id):
        name = CLASS_NAMES[value] if 0 <= value < len(CLASS_NAMES) else "unknown"
        position = overrides.get(name, targeting_for(name))
        rows = class_id == value
        horizontal[rows] = position.horizontal
        vertical[rows] = position.vertical
    return horizontal, vertical


def make_message(
    camera_id: str,
    sequence: int,
    timestamp: float,
    frame: int,
    detections: Detections,
    reference: Reference,
    targeting: dict[str, TargetingPosition] | None = None,
    targeter: Targeter | None = None,
    drop_hidden_feet: bool = False,
) -> CameraMessage:
    """Localise one frame's detections through the reference image and build the message.

    Args:
        camera_id: the camera's name.
        sequence: per-camera message counter.
        timestamp: capture time, seconds.
        frame: frame number.
        detections: the frame's boxes.
        reference: the camera's reference image.
        targeting: per-class targeting overrides (defaults: :data:`DEFAULT_TARGETING`).
        targeter: optional object choosing the target pixels itself (for example a
            :class:`cblrs.geometric_targeting.GeometricTargeter`, which aims at the
            footprint centre); then no depth offset is applied. The border policy is the
            same as for the default targeting.
        drop_hidden_feet: no location for a box whose target lies inside the box of a
            nearer object (:func:`feet_hidden`); for detector boxes, which end where the
            visible part ends.

    Returns:
        The message; a detection whose target pixel sees no plane (or lies outside the
        image) carries colour (0, 0, 0).
    """
    if targeter is not None:
        pixels, inside = targeter.target_pixels(detections)
        colours = _box_colours(
            detections.xyxy, detections.class_id, reference, targeting, drop_hidden_feet,
            targeted=(pixels, inside), confidence=detections.confidence,
        )
    else:
        colours = _box_colours(
            detections.xyxy, detections.class_id, reference, targeting, drop_hidden_feet,
            confidence=detections.confidence,
        )
    return CameraMessage(
        camera_id=camera_id,
        sequence=sequence,
        timestamp=timestamp,
        frame=frame,
        xyxy=detections.xyxy,
        confidence=detections.confidence,
        class_id=detections.class_id,
        colour=colours,
    )


def make_messages(
    camera_id: str,
    frames: Sequence[tuple[int, float, int]],
    detections: Sequence[Detections],
    reference: Reference,
    targeting: dict[str, TargetingPosition] | None = None,
    targeter: Targeter | None = None,
    drop_hidden_feet: bool = False,
) -> list[CameraMessage]:
    """:func:`make_message` for many frames of one camera: the same messages.

    The boxes of all frames are targeted and looked up at once (what a replay of a recorded
    camera can do; a live camera sends frame by frame). Every step is row by row except the
    hidden-feet rule, which compares the boxes of one frame, so the colours are those of
    :func:`make_message` frame by frame.

    Args:
        camera_id: the camera's name.
        frames: per message ``(sequence, timestamp, frame)``.
        detections: per message that frame's boxes (as many as ``frames``).
        reference, targeting, targeter, drop_hidden_feet: as for :func:`make_message`; a
            targeter chooses pixels frame by frame.

    Returns:
        One message per frame, in the order given.
    """
    if len(frames) != len(detections):
        raise ValueError(
            f"need one set of detections per frame ({len(frames)}), got {len(detections)}"
        )
    if targeter is not None or not frames:
        return [
            make_message(camera_id, sequence, timestamp, frame, boxes, reference, targeting,
                         targeter, drop_hidden_feet)
            for (sequence, timestamp, frame), boxes in zip(frames, detections, strict=True)
        ]
    xyxy = np.concatenate([boxes.xyxy for boxes in detections])
    class_id = np.concatenate([boxes.class_id for boxes in detections])
    confidence = np.concatenate([boxes.confidence for boxes in detections])
    ends = np.cumsum([len(boxes) for boxes in detections])
    colours = _box_colours(
        xyxy, class_id, reference, targeting, drop_hidden_feet, frame_ends=ends,
        confidence=confidence,
    )
    starts = ends - np.array([len(boxes) for boxes in detections])
    return [
        CameraMessage(
            camera_id=camera_id,
            sequence=sequence,
            timestamp=timestamp,
            frame=frame,
            xyxy=boxes.xyxy,
            confidence=boxes.confidence,
            class_id=boxes.class_id,
            colour=colours[start:end],
        )
        for (sequence, timestamp, frame), boxes, start, end in zip(
            frames, detections, starts.tolist(), ends.tolist(), strict=True
        )
    ]


def _box_colours(
    xyxy: np.ndarray,
    class_id: np.ndarray,
    reference: Reference,
    targeting: dict[str, TargetingPosition] | None,
    drop_hidden_feet: bool,
    targeted: tuple[np.ndarray, np.ndarray] | None = None,
    frame_ends: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 3) int64 colours of boxes, the policy of :func:`make_message`.

    ``targeted``: a targeter's ``(pixels, inside)``, replacing the class targeting and its
    depth offsets. ``frame_ends``: the boxes are several frames' one after another, frame k
    ending before row ``frame_ends[k]`` (the hidden-feet rule compares boxes of one frame);
    None: one frame. ``confidence``: the boxes' scores, for the hidden-feet rule.
    """
    horizontal, vertical = targeting_columns(class_id, targeting)
    offset = depth_offsets(class_id, targeting)
    horizontal_matters = offset > 0
    vertical = np.where(offset > 0, OFFSET_TARGETING.vertical, vertical)
    horizontal = np.where(offset > 0, OFFSET_TARGETING.horizontal, horizontal)
    pixels, inside = target_pixels(xyxy, horizontal, vertical, image_size=reference.image_size)
    if targeted is not None:
        pixels, inside = targeted
        offset = np.zeros(len(xyxy))
    colours, valid = reference.colours_at(pixels)
    cut = cut_by_border(xyxy, vertical, horizontal_matters, reference.image_size)
    if drop_hidden_feet:
        if frame_ends is None:
            cut |= feet_hidden(xyxy, pixels, vertical, confidence=confidence)
        else:
            starts = np.concatenate([[0], frame_ends[:-1]]).tolist()
            for start, end in zip(starts, frame_ends.tolist(), strict=True):
                cut[start:end] |= feet_hidden(
                    xyxy[start:end], pixels[start:end], vertical[start:end],
                    confidence=None if confidence is None else confidence[start:end],
                )
    colours[~(valid & inside) | cut] = 0
    shift = (offset > 0) & ~cut
    if shift.any():
        colours[shift] = _push_away(reference, xyxy[shift], pixels[shift],
                                    colours[shift], offset[shift])
    return colours


def cut_by_border(
    xyxy: np.ndarray, vertical: np.ndarray, sides_matter: np.ndarray, image_size: tuple[int, int]
) -> np.ndarray:
    """(N,) bool: boxes whose target edge touches the image border (within a pixel).

    Args:
        xyxy: (N, 4) pixel boxes.
        vertical: (N,) vertical targeting fractions (> 0.5 aims at the bottom part).
        sides_matter: (N,) bool, also count boxes touching the left or right border.
        image_size: (width, height).
    """
    width, height = image_size
    margin = 1.5  # clipped boxes end at -0.5 or size - 0.5 (pixel area), allow rounding
    with np.errstate(invalid="ignore"):
        bottom = (vertical > 0.5) & (xyxy[:, 3] >= height - margin)
        top = (vertical < 0.5) & (xyxy[:, 1] <= margin - 1.0)
        sides = sides_matter & ((xyxy[:, 0] <= margin - 1.0) | (xyxy[:, 2] >= width - margin))
    return bottom | top | sides


def feet_hidden(
    xyxy: np.ndarray,
    pixels: np.ndarray,
    vertical: np.ndarray,
    tolerance: float = HIDDEN_FEET_TOLERANCE,
    confidence: np.ndarray | None = None,
    sure: float = SURE_CONFIDENCE,
) -> np.ndarray:
    """(N,) bool: targets in the lower part of a box that lie inside a nearer object's box.

    On a ground plane a nearer object's box reaches lower in the image; when the target of
    box A lies inside box B and B's bottom is lower than A's target by more than
    ``tolerance`` x A's height, B stands in front of A's ground contact.

    Args:
        xyxy: (N, 4) pixel boxes.
        pixels: (N, 2) target pixels.
        vertical: (N,) vertical targeting fractions; only targets below the box centre count.
        tolerance: how much lower B must reach, as a fraction of A's height.
        confidence: (N,) detector scores, or None (every box may hide another); a box
            scored below ``sure`` hides only boxes scored lower still (a doubtful box does
            not take a sure box's location).
        sure: the score from which a box may hide any other.
    """
    count = len(xyxy)
    if count < 2:
        return np.zeros(count, dtype=bool)
    with np.errstate(invalid="ignore"):
        x, y = pixels[:, 0], pixels[:, 1]
        margin = tolerance * (xyxy[:, 3] - xyxy[:, 1])
        inside = (
            (x[:, None] >= xyxy[None, :, 0])
            & (x[:, None] <= xyxy[None, :, 2])
            & (y[:, None] >= xyxy[None, :, 1])
            & (xyxy[None, :, 3] > y[:, None] + margin[:, None])
        )
    np.fill_diagonal(inside, False)
    if confidence is not None:
        inside &= confidence[None, :] >= np.minimum(confidence[:, None], sure)
    return (vertical > 0.5) & inside.any(axis=1)


def depth_offsets(
    class_id: np.ndarray, overrides: dict[str, TargetingPosition] | None = None
) -> np.ndarray:
    """Per-detection ground offset (metres) away from the camera; 0 for overridden classes."""
    overrides = overrides or {}
    offset = np.zeros(len(class_id))
    for value in unique_integers(class_id):
        name = CLASS_NAMES[value] if 0 <= value < len(CLASS_NAMES) else "unknown"
        if name not in overrides:
            offset[class_id == value] = GROUND_DEPTH_OFFSET_M.get(name, 0.0)
    return offset


def _push_away(
    reference: Reference,
    xyxy: np.ndarray,
    pixels: np.ndarray,
    colours: np.ndarray,
    offset_m: np.ndarray,
) -> np.ndarray:
    """Colours of the target points moved ``offset_m`` away from the camera on the plane.

    The direction is from the target's ground point to that of a pixel higher up in the box;
    where either has no location, or the moved point leaves its plane, the colour is kept.
    """
    colours = colours.copy()
    world_xy, valid, plane_id = reference.planes.decode(colours)
    step = np.maximum(_DIRECTION_STEP * (xyxy[:, 3] - xyxy[:, 1]), 2.0)
    above = pixels - np.column_stack([np.zeros(len(step)), step])
    colours_above, _ = reference.colours_at(above)
    world_above, valid_above, plane_above = reference.planes.decode(colours_above)
    direction = world_above - world_xy
    length = np.linalg.norm(direction, axis=1)
    with np.errstate(invalid="ignore"):
        usable = valid & valid_above & (plane_above == plane_id) & (length > 0)
    for plane in reference.planes:
        rows = np.flatnonzero(usable & (plane_id == plane.plane_id))
        if len(rows) == 0:
            continue
        moved = world_xy[rows] + direction[rows] / length[rows, None] * offset_m[rows, None]
        encoded, inside = plane.encode(moved)
        colours[rows[inside]] = encoded[inside]
    return colours
