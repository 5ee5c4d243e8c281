"""Detect on tiles chosen from the reference image: small far people at native resolution.

A detector with a 416 x 416 input sees a 1920 x 1080 frame shrunk 4.6 times; a person
100 pixels tall becomes 22 model pixels and is nearly invisible. Running the model on
tiles at the frame's own resolution finds them, but tiling the whole frame costs 15
inferences. The reference image knows better: it says where the plane is visible
(B != 0) and, at every pixel, how many metres of ground one pixel spans. Along an image
row of a camera without roll that span is the depth divided by the focal length, so an
object of height ``H`` metres standing there is about ``H / span`` pixels tall (a little
less on a steeply tilted camera). :func:`plan_tiles` uses this to give every part of the
visible plane the coarsest scale at which a person standing there is at least
``min_object_px`` model pixels tall:

* the scales are an octave pyramid anchored at the native resolution: 1, 1/2, 1/4, ...
  down to the whole frame letterboxed (a level within a factor sqrt(2) of the
  whole-frame scale is left out: the whole frame does its job);
* the whole frame runs once if any part of the plane needs no more than it;
* each finer level covers the image region of the people standing where it is needed
  (their boxes, estimated from the span) with model-sized tiles that overlap by the
  largest such box, so every such person lies whole in at least one tile.

:class:`TiledDetector` runs the detector on the plan's tiles and merges: boxes touching an
inner tile edge are dropped when a box of another tile holds them (the person was cut
there but is whole elsewhere), then class-aware NMS runs over all tiles.

``min_object_px`` defaults to 50: the height of a person (box aspect about 0.4) whose
box covers 32 x 32 pixels, COCO's limit for "small" objects, on which COCO-trained
detectors are known to be weak (their small-object AP is a fraction of the rest).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import Detections
from cblrs.detectors.base import box_cover, non_maximum_suppression
from cblrs.errors import CblrsError
from cblrs.reference import Reference

logger = logging.getLogger(__name__)

PERSON_HEIGHT_M = 1.7
PERSON_ASPECT = 0.41
"""Typical width / height of a standing person's box."""
DEFAULT_MIN_OBJECT_PX = 32.0 / math.sqrt(PERSON_ASPECT)
"""Smallest person the detector should see, model pixels tall (COCO's small-object limit)."""
_GRID_PX = 8  # the reference is sampled every this many pixels
_CUT_MARGIN_PX = 2.0  # a box this close to an inner tile edge counts as cut there
_HELD_WHOLE = 0.6  # a cut box is dropped when this share of it lies in a box of another tile


@dataclass(frozen=True)
class Tile:
    """One crop of the frame and the scale the detector sees it at.

    Attributes:
        x0, y0, x1, y1: the crop in image pixels (x1, y1 exclusive).
        scale: model input pixels per image pixel once the crop is letterboxed.
        inner_edges: (left, top, right, bottom) True where that edge lies inside the image.
    """

    x0: int
    y0: int
    x1: int
    y1: int
    scale: float
    inner_edges: tuple[bool, bool, bool, bool]

    @property
    def is_whole_frame(self) -> bool:
        return not any(self.inner_edges)


@dataclass(frozen=True)
class TilePlan:
    """The tiles of one camera, whole frame (if any) first.

    Attributes:
        image_size: (width, height) of the frames.
        model_size: (width, height) of the detector's input.
        tiles: the crops, coarsest first.
        min_object_px: the smallest person, in model pixels, the plan provides for.
    """

    image_size: tuple[int, int]
    model_size: tuple[int, int]
    tiles: tuple[Tile, ...]
    min_object_px: float

    def __len__(self) -> int:
        return len(self.tiles)

    def describe(self) -> str:
        """One line, e.g. ``whole frame + 3 tiles at 1/2 + 6 tiles at 1``."""
        parts = []
        if any(tile.is_whole_frame for tile in self.tiles):
            parts.append("whole frame")
        scales = sorted({tile.scale for tile in self.tiles if not tile.is_whole_frame})
        for scale in scales:
            count = sum(1 for t in self.tiles if t.scale == scale and not t.is_whole_frame)
            label = "1" if scale == 1 else f"1/{round(1 / scale)}"
            parts.append(f"{count} tile{'s' if count > 1 else ''} at {label}")
        return " + ".join(parts) if parts else "no tiles"


def whole_frame_plan(image_size: tuple[int, int], model_size: tuple[int, int]) -> TilePlan:
    """The plan of no tiling: the whole frame letterboxed once."""
    width, height = image_size
    scale = min(model_size[0] / width, model_size[1] / height)
    tile = Tile(0, 0, width, height, scale, (False, False, False, False))
    return TilePlan((width, height), model_size, (tile,), 0.0)


def object_heights_px(
    reference: Reference, object_height_m: float = PERSON_HEIGHT_M, grid_px: int = _GRID_PX
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Where the plane is visible, on a grid, and how tall an object standing there looks.

    Args:
        reference: the camera's reference image.
        object_height_m: the object's height, metres.
        grid_px: grid step in pixels.

    Returns:
        ``(u, v, height_px)``: (K,) pixel columns and rows of the grid points that see a
        plane, and (K,) the expected image height of the object with its feet there.
    """
    width, height = reference.image_size
    columns = np.arange(grid_px // 2, width - 1, grid_px, dtype=np.float64)
    rows = np.arange(grid_px // 2, height, grid_px, dtype=np.float64)
    grid_u, grid_v = np.meshgrid(columns, rows)
    pixels = np.column_stack([grid_u.ravel(), grid_v.ravel()])
    step = min(4.0, float(width - 1) - pixels[:, 0].max())
    step = max(step, 1.0)
    world, valid, plane = reference.planes.decode(reference.colours_at(pixels)[0])
    world_right, valid_right, plane_right = reference.planes.decode(
        reference.colours_at(pixels + np.array([step, 0.0]))[0]
    )
    with np.errstate(invalid="ignore"):
        span = np.linalg.norm(world_right - world, axis=1) / step
        usable = valid & valid_right & (plane == plane_right) & (span > 0)
    return (
        pixels[usable, 0],
        pixels[usable, 1],
        object_height_m / span[usable],
    )


def plan_tiles(
    reference: Reference,
    model_size: tuple[int, int],
    min_object_px: float = DEFAULT_MIN_OBJECT_PX,
    object_height_m: float = PERSON_HEIGHT_M,
    max_scale: float = 1.0,
) -> TilePlan:
    """Tiles that show every person standing on the visible plane large enough.

    Args:
        reference: the camera's reference image (its size is the frames' size).
        model_size: (width, height) of the detector's input.
        min_object_px: smallest object height, model pixels, to provide for.
        object_height_m: the height of the objects to find (a person).
        max_scale: finest scale (model pixels per image pixel); 1 is native resolution.

    Returns:
        The plan; the whole frame alone when the reference sees no plane or the whole
        frame already shows everyone large enough.
    """
    if not min_object_px > 0 or not object_height_m > 0 or not max_scale > 0:
        raise CblrsError("min_object_px, object_height_m and max_scale must be positive.")
    width, height = reference.image_size
    model_width, model_height = model_size
    whole = whole_frame_plan((width, height), model_size)
    frame_scale = whole.tiles[0].scale
    scales = [frame_scale]
    level = max_scale
    finer: list[float] = []
    while level > frame_scale * math.sqrt(2):
        finer.append(level)
        level /= 2
    scales += sorted(finer)

    u, v, heights = object_heights_px(reference, object_height_m)
    if len(u) == 0:
        logger.info("the reference sees no plane; detecting on the whole frame only")
        return whole
    required = min_object_px / heights
    assigned = np.searchsorted(np.array(scales), required - 1e-12)
    assigned = np.minimum(assigned, len(scales) - 1)

    tiles: list[Tile] = []
    if np.any(assigned == 0):
        tiles.append(whole.tiles[0])
    for index in range(1, len(scales)):
        rows = assigned == index
        if not rows.any():
            continue
        scale = scales[index]
        tiles.extend(
            _cover(u[rows], v[rows], heights[rows], scale, (width, height), model_size)
        )
    if not tiles:
        return whole
    plan = TilePlan((width, height), (model_width, model_height), tuple(tiles), min_object_px)
    logger.debug("tile plan %dx%d: %s", width, height, plan.describe())
    return plan


def _cover(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    heights: NDArray[np.float64],
    scale: float,
    image_size: tuple[int, int],
    model_size: tuple[int, int],
) -> list[Tile]:
    """Model-sized tiles at ``scale`` covering the boxes of people with feet at (u, v)."""
    width, height = image_size
    tile_width = min(width, round(model_size[0] / scale))
    tile_height = min(height, round(model_size[1] / scale))
    half_width = heights * PERSON_ASPECT / 2 * 1.5  # arms and stride widen the box
    left = np.clip(u - half_width, 0, width)
    right = np.clip(u + half_width, 0, width)
    top = np.clip(v - heights * 1.05, 0, height)
    bottom = np.clip(v + 0.05 * heights, 0, height)
    overlap_x = min(float(np.max(right - left)), tile_width / 2)
    overlap_y = min(float(np.max(bottom - top)), tile_height / 2)
    x_starts = _starts(float(left.min()), float(right.max()), tile_width, overlap_x, width)
    y_starts = _starts(float(top.min()), float(bottom.max()), tile_height, overlap_y, height)
    tiles = []
    for y0 in y_starts:
        for x0 in x_starts:
            x1, y1 = x0 + tile_width, y0 + tile_height
            # Keep a tile only when some person box lies in it.
            inside = (left < x1) & (right > x0) & (top < y1) & (bottom > y0)
            if not inside.any():
                continue
            edges = (x0 > 0, y0 > 0, x1 < width, y1 < height)
            tiles.append(Tile(x0, y0, x1, y1, scale, edges))
    return tiles


def _starts(low: float, high: float, size: int, overlap: float, limit: int) -> list[int]:
    """Tile origins spanning [low, high] with tiles of ``size`` overlapping by ``overlap``."""
    span = high - low
    if span <= size:
        start = round(min(max((low + high - size) / 2, 0), limit - size))
        return [start]
    count = math.ceil((span - overlap) / (size - overlap))
    step = (span - size) / (count - 1) if count > 1 else 0.0
    starts = [round(min(max(low + k * step, 0), limit - size)) for k in range(count)]
    return sorted(set(starts))


class TiledDetector:
    """Run a detector on a :class:`TilePlan`'s crops and merge the boxes.

    Args:
        detector: an object with ``candidates(image) -> Detections`` (boxes above the
            confidence threshold, before NMS) and ``iou`` (the NMS threshold), such as
            :class:`cblrs.detectors.onnx.OnnxDetector`.
        plan: the tiles (from :func:`plan_tiles`).
    """

    def __init__(self, detector, plan: TilePlan):
        self.detector = detector
        self.plan = plan

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        """Boxes of one frame, in frame pixels, merged over the tiles (see the module notes)."""
        height, width = image.shape[:2]
        if (width, height) != self.plan.image_size:
            raise CblrsError(
                f"the frame is {width}x{height} but the tile plan (from the reference image) "
                f"is for {self.plan.image_size[0]}x{self.plan.image_size[1]}."
            )
        parts: list[Detections] = []
        tile_index: list[NDArray[np.int64]] = []
        cut: list[NDArray[np.bool_]] = []
        for index, tile in enumerate(self.plan.tiles):
            crop = image[tile.y0 : tile.y1, tile.x0 : tile.x1]
            found = self.detector.candidates(np.ascontiguousarray(crop))
            kept = non_maximum_suppression(
                found.xyxy, found.confidence, found.class_id, self.detector.iou
            )
            found = found[kept]
            xyxy = found.xyxy + np.array([tile.x0, tile.y0, tile.x0, tile.y0], dtype=np.float64)
            parts.append(Detections(xyxy, found.confidence, found.class_id))
            tile_index.append(np.full(len(found), index, dtype=np.int64))
            cut.append(_touches_inner_edge(xyxy, tile))
        merged = Detections.concatenate(parts)
        if len(merged) == 0:
            return merged
        tiles = np.concatenate(tile_index)
        is_cut = np.concatenate(cut)
        drop = np.zeros(len(merged), dtype=bool)
        if is_cut.any():
            whole = ~is_cut
            cover = box_cover(merged.xyxy[is_cut], merged.xyxy[whole])
            other_tile = tiles[is_cut][:, None] != tiles[whole][None, :]
            same_class = merged.class_id[is_cut][:, None] == merged.class_id[whole][None, :]
            held = np.any((cover >= _HELD_WHOLE) & other_tile & same_class, axis=1)
            drop[np.flatnonzero(is_cut)[held]] = True
        merged = merged[~drop]
        kept = non_maximum_suppression(
            merged.xyxy, merged.confidence, merged.class_id, self.detector.iou
        )
        return merged[kept]


def _touches_inner_edge(xyxy: NDArray[np.float64], tile: Tile) -> NDArray[np.bool_]:
    left, top, right, bottom = tile.inner_edges
    margin = _CUT_MARGIN_PX
    touches = np.zeros(len(xyxy), dtype=bool)
    if left:
        touches |= xyxy[:, 0] <= tile.x0 + margin
    if top:
        touches |= xyxy[:, 1] <= tile.y0 + margin
    if right:
        touches |= xyxy[:, 2] >= tile.x1 - margin
    if bottom:
        touches |= xyxy[:, 3] >= tile.y1 - margin
    return touches
