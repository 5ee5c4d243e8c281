"""A simulated detector over ground-truth boxes: misses, box noise and false positives.

Real detectors miss people, place boxes a little off and fire on background. This module
degrades a scene's annotated boxes in those three ways, seeded and reproducibly, so trackers
can be scored under realistic detector errors without a detector:

* **drop**: each box is removed independently with probability ``drop``;
* **jitter**: each box edge moves by Gaussian noise, sigma = ``jitter`` x the box width (left
  and right edges) or height (top and bottom edges);
* **false positives**: per frame and camera, a Poisson(``false_positives``) number of extra
  boxes with ``object_id`` -1, lying inside the image, with a size, class and confidence drawn
  from that camera's real boxes (so they look like the real ones to a tracker).

The three effects draw from independent random streams derived from ``seed``: changing one
rate does not change which boxes the others affect.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from cblrs.datasets.scene import Scene
from cblrs.detections import Detections, class_id_of
from cblrs.errors import DatasetError

logger = logging.getLogger(__name__)

# Fallback false-positive box when a scene has no boxes at all: a standing person of a
# fifth of the image height.
_DEFAULT_HEIGHT_FRACTION = 0.2
_DEFAULT_ASPECT = 0.4  # width / height


@dataclass(frozen=True)
class _BoxPool:
    """Sizes, classes and confidences of real boxes, to draw false positives from."""

    width: np.ndarray
    height: np.ndarray
    class_id: np.ndarray
    confidence: np.ndarray

    def __len__(self) -> int:
        return len(self.width)


def simulate_detections(
    scene: Scene,
    drop: float = 0.0,
    jitter: float = 0.0,
    false_positives: float = 0.0,
    seed: int = 0,
) -> Scene:
    """The scene with its detections degraded as a real detector would.

    Args:
        scene: the scene whose (ground-truth) boxes are degraded; not modified.
        drop: probability in [0, 1] that a box is missed, independently per box.
        jitter: Gaussian noise on each box edge, as a fraction (>= 0) of the box width
            (x edges) or height (y edges). Edges are re-ordered if noise crosses them.
        false_positives: mean number (>= 0) of spurious boxes per frame and camera (Poisson).
        seed: seed of the random streams; the same arguments give the same scene.

    Returns:
        A new scene with the same cameras, frames and ground truth and degraded
        ``detections``; with all rates zero, ``scene`` itself.

    Raises:
        DatasetError: a rate is out of range or not finite.

    Example:
        >>> noisy = simulate_detections(scene, drop=0.2, jitter=0.05, seed=1)  # doctest: +SKIP
    """
    _check_rate("drop", drop, upper=1.0)
    _check_rate("jitter", jitter)
    _check_rate("false_positives", false_positives)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise DatasetError(f"seed must be a non-negative integer, got {seed!r}.")
    if drop == 0 and jitter == 0 and false_positives == 0:
        return scene

    drop_seed, jitter_seed, false_seed = np.random.SeedSequence(int(seed)).spawn(3)
    drop_random = np.random.default_rng(drop_seed)
    jitter_random = np.random.default_rng(jitter_seed)
    false_random = np.random.default_rng(false_seed)
    pools = _box_pools(scene) if false_positives > 0 else []

    degraded: list[list[Detections]] = []
    kept = spurious = 0
    for per_camera in scene.detections:
        frame_detections = []
        for camera_index, detections in enumerate(per_camera):
            # Draw for every box even at rate 0 so each stream's use is independent of the
            # other rates.
            keep = drop_random.random(len(detections)) >= drop
            noise = jitter_random.standard_normal((len(detections), 4))
            xyxy = detections.xyxy
            if jitter > 0:
                width = np.abs(xyxy[:, 2] - xyxy[:, 0])
                height = np.abs(xyxy[:, 3] - xyxy[:, 1])
                size = np.stack([width, height, width, height], axis=1)
                xyxy = _ordered(xyxy + jitter * size * noise)
            result = replace(detections, xyxy=xyxy)[keep]
            kept += len(result)
            if false_positives > 0:
                count = int(false_random.poisson(false_positives))
                if count:
                    extra = _false_boxes(
                        false_random, count, pools[camera_index],
                        scene.cameras[camera_index].image_size,
                    )
                    spurious += count
                    result = Detections.concatenate([result, extra])
            frame_detections.append(result)
        degraded.append(frame_detections)
    logger.debug(
        "simulated detector (drop %.3f, jitter %.3f, false positives %.3f, seed %d): "
        "%d boxes kept, %d false positives",
        drop, jitter, false_positives, seed, kept, spurious,
    )
    return replace(scene, detections=degraded)


def _check_rate(name: str, value: float, upper: float | None = None) -> None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{name} must be a number, got {value!r}.") from None
    if not math.isfinite(number) or number < 0 or (upper is not None and number > upper):
        limit = f"in [0, {upper:g}]" if upper is not None else ">= 0"
        raise DatasetError(f"{name} must be {limit}, got {value!r}.")


def _ordered(xyxy: np.ndarray) -> np.ndarray:
    """Boxes with x_min <= x_max and y_min <= y_max."""
    return np.stack(
        [
            np.minimum(xyxy[:, 0], xyxy[:, 2]),
            np.minimum(xyxy[:, 1], xyxy[:, 3]),
            np.maximum(xyxy[:, 0], xyxy[:, 2]),
            np.maximum(xyxy[:, 1], xyxy[:, 3]),
        ],
        axis=1,
    ).reshape(-1, 4)


def _box_pools(scene: Scene) -> list[_BoxPool]:
    """Per camera, the real boxes to copy sizes from (all cameras' boxes if it has none)."""
    per_camera: list[list[Detections]] = [[] for _ in scene.cameras]
    for frame_detections in scene.detections:
        for camera_index, detections in enumerate(frame_detections):
            per_camera[camera_index].append(detections)
    pools = [_pool_of(Detections.concatenate(parts)) for parts in per_camera]
    everything = _pool_of(
        Detections.concatenate([d for parts in per_camera for d in parts])
    )
    return [pool if len(pool) else everything for pool in pools]


def _pool_of(detections: Detections) -> _BoxPool:
    width = detections.xyxy[:, 2] - detections.xyxy[:, 0]
    height = detections.xyxy[:, 3] - detections.xyxy[:, 1]
    usable = (width > 0) & (height > 0)
    return _BoxPool(
        width[usable], height[usable], detections.class_id[usable], detections.confidence[usable]
    )


def _false_boxes(
    random: np.random.Generator, count: int, pool: _BoxPool, image_size: tuple[int, int]
) -> Detections:
    """``count`` boxes inside the image with sizes/classes/confidences drawn from ``pool``."""
    image_width, image_height = float(image_size[0]), float(image_size[1])
    if len(pool):
        index = random.integers(0, len(pool), count)
        width, height = pool.width[index], pool.height[index]
        class_id, confidence = pool.class_id[index], pool.confidence[index]
    else:
        height = np.full(count, _DEFAULT_HEIGHT_FRACTION * image_height)
        width = _DEFAULT_ASPECT * height
        class_id = np.full(count, class_id_of("person"), dtype=np.int64)
        confidence = np.ones(count)
    # Boxes larger than the image shrink to fit; the rest lie fully inside it.
    width = np.minimum(width, image_width - 1.0)
    height = np.minimum(height, image_height - 1.0)
    x_min = random.uniform(0.0, 1.0, count) * (image_width - 1.0 - width)
    y_min = random.uniform(0.0, 1.0, count) * (image_height - 1.0 - height)
    return Detections(
        xyxy=np.stack([x_min, y_min, x_min + width, y_min + height], axis=1),
        confidence=confidence,
        class_id=class_id,
        object_id=np.full(count, -1, dtype=np.int64),
    )
