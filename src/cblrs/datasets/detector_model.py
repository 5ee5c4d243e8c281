"""A more realistic simulated detector: misses where detectors miss, false positives that stay.

:func:`cblrs.datasets.simulate_detections` drops boxes independently and fires false positives
anywhere, at random; a tuner can learn to ignore such errors, and what it learns does not
transfer to a real detector, whose errors are structured:

* **misses correlate with occlusion and distance**: a box mostly covered by nearer boxes
  (lower bottom edge in the same image) or small (far) is missed more often, and a miss
  persists for some frames (the person stays hidden or small);
* **boxes of partly hidden people are truncated**: when a nearer person hides the lower part,
  the detector's box often ends at the occluder's top, so its bottom edge (the foot point)
  is too high and the ground position lands nearer the camera;
* **false positives persist**: each camera has a few fixed places (a sign, a bollard, a
  reflection) where the detector fires in most frames at about the same box, besides rare
  transient ones; a persistent one is consistent in time but seen by one camera only;
* **box noise**: Gaussian noise on each edge, a fraction of the box size.

Everything is seeded; the same arguments give the same scene. Boxes keep their ground-truth
``object_id`` (false positives have -1). It works on any :class:`Scene` whose boxes carry
object ids (data sets, synthetic worlds).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cblrs.datasets.scene import Scene
from cblrs.detections import Detections
from cblrs.errors import DatasetError


@dataclass(frozen=True)
class DetectorModel:
    """Rates of :func:`realistic_detections` (defaults: a mid-size detector on crowded scenes).

    Attributes:
        miss: probability of missing a fully visible, near box.
        occluded_miss: extra miss probability of a box fully covered by nearer boxes (scaled
            by the covered fraction).
        far_miss: extra miss probability of a box a third as tall as the camera's median
            (scaled linearly from the median height down).
        persistence: probability that a miss continues at the next frame.
        truncation: probability that a box whose lower part is hidden ends at its occluder.
        jitter: Gaussian noise on each edge as a fraction of the box width / height.
        false_sites: persistent false-positive places per camera.
        false_site_rate: probability that a persistent place fires at a frame.
        transient_false: mean transient false positives per frame and camera.
    """

    miss: float = 0.05
    occluded_miss: float = 0.6
    far_miss: float = 0.35
    persistence: float = 0.6
    truncation: float = 0.5
    jitter: float = 0.04
    false_sites: int = 2
    false_site_rate: float = 0.6
    transient_false: float = 0.1

    def __post_init__(self) -> None:
        for name in ("miss", "occluded_miss", "far_miss", "persistence", "truncation",
                     "false_site_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise DatasetError(f"{name} must be in [0, 1], got {value}.")
        if self.jitter < 0 or self.transient_false < 0 or self.false_sites < 0:
            raise DatasetError("jitter, transient_false and false_sites must be >= 0.")


def covered_fraction(xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of each box covered by nearer boxes, and the top of its lowest occluder.

    A box is nearer when its bottom edge is lower in the image (larger y). The cover is the
    largest single overlap, a box-level approximation.

    Args:
        xyxy: (N, 4) pixel boxes of one camera and frame.

    Returns:
        ``(covered (N,), occluder_top (N,))``: fraction 0..1, and the top edge (pixels) of the
        nearer box that covers the most of its lower half (NaN: none).
    """
    count = len(xyxy)
    covered = np.zeros(count)
    occluder_top = np.full(count, np.nan)
    if count < 2:
        return covered, occluder_top
    x1, y1, x2, y2 = (xyxy[:, k] for k in range(4))
    width = np.maximum(np.minimum(x2[:, None], x2[None]) - np.maximum(x1[:, None], x1[None]),
                       0.0)
    height = np.maximum(np.minimum(y2[:, None], y2[None]) - np.maximum(y1[:, None], y1[None]),
                        0.0)
    area = np.maximum((x2 - x1) * (y2 - y1), 1e-9)
    nearer = y2[None, :] > y2[:, None]  # [i, j]: j is nearer than i
    overlap = np.where(nearer, width * height, 0.0) / area[:, None]
    covered = np.clip(overlap.max(axis=1), 0.0, 1.0)
    # An occluder of the lower part: nearer, covering at least half the box's width, with
    # its top between the box's middle and bottom.
    middle = (y1 + y2) / 2
    lower = nearer & (width >= 0.5 * (x2 - x1)[:, None]) & (y1[None, :] >= middle[:, None]) & (
        y1[None, :] < y2[:, None])
    has = lower.any(axis=1)
    tops = np.where(lower, y1[None, :], np.inf).min(axis=1)
    occluder_top[has] = tops[has]
    return covered, occluder_top


def realistic_detections(scene: Scene, seed: int = 0, model: DetectorModel | None = None
                         ) -> Scene:
    """The scene's boxes as a realistic detector would report them (see the module notes).

    Args:
        scene: its boxes should carry ``object_id`` (misses persist per object); not modified.
        seed: seed of every random draw.
        model: the rates; None uses :class:`DetectorModel`'s defaults.

    Returns:
        A new scene with the same cameras, frames and ground truth and degraded detections.
    """
    model = model or DetectorModel()
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise DatasetError(f"seed must be a non-negative integer, got {seed!r}.")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7919]))
    camera_count = len(scene.cameras)
    heights = [np.concatenate([row[c].xyxy[:, 3] - row[c].xyxy[:, 1] for row in scene.detections]
                              + [np.zeros(0)]) for c in range(camera_count)]
    median_height = [float(np.median(h)) if len(h) else 100.0 for h in heights]
    sites = [_false_sites(rng, model.false_sites, scene.cameras[c].image_size, median_height[c])
             for c in range(camera_count)]
    missing: list[dict[int, bool]] = [{} for _ in range(camera_count)]
    degraded: list[list[Detections]] = []
    for row in scene.detections:
        frame_boxes = []
        for camera, detections in enumerate(row):
            xyxy = detections.xyxy.copy()
            covered, occluder_top = covered_fraction(xyxy)
            height = xyxy[:, 3] - xyxy[:, 1]
            small = np.clip((median_height[camera] - height) / (2 * median_height[camera] / 3),
                            0.0, 1.0)
            fresh = 1 - (1 - model.miss) * (1 - model.occluded_miss * covered) * (
                1 - model.far_miss * small)
            previous = np.array([missing[camera].get(int(one), False)
                                 for one in detections.object_id.tolist()], bool)
            probability = np.where(previous, model.persistence + (1 - model.persistence) * fresh,
                                   fresh)
            missed = rng.random(len(xyxy)) < probability
            missing[camera] = {int(one): bool(flag) for one, flag in zip(
                detections.object_id.tolist(), missed.tolist(), strict=True) if one >= 0}
            truncate = np.isfinite(occluder_top) & (rng.random(len(xyxy)) < model.truncation)
            xyxy[truncate, 3] = np.maximum(occluder_top[truncate],
                                           xyxy[truncate, 1] + 0.3 * height[truncate])
            size = np.stack([xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1]] * 2, axis=1)
            xyxy = xyxy + model.jitter * size * rng.standard_normal(xyxy.shape)
            xyxy = np.column_stack([np.minimum(xyxy[:, 0], xyxy[:, 2]),
                                    np.minimum(xyxy[:, 1], xyxy[:, 3]),
                                    np.maximum(xyxy[:, 0], xyxy[:, 2]),
                                    np.maximum(xyxy[:, 1], xyxy[:, 3])])
            confidence = np.clip(0.9 - 0.4 * covered - 0.3 * small
                                 + 0.05 * rng.standard_normal(len(xyxy)), 0.3, 1.0)
            kept = replace(detections, xyxy=xyxy, confidence=confidence)[~missed]
            false = _false_boxes(rng, model, sites[camera], detections,
                                 scene.cameras[camera].image_size, median_height[camera])
            frame_boxes.append(Detections.concatenate([kept, false]) if len(false) else kept)
        degraded.append(frame_boxes)
    return replace(scene, detections=degraded)


def _false_sites(rng: np.random.Generator, count: int, image_size: tuple[int, int],
                 height: float) -> np.ndarray:
    """(count, 4) fixed false-positive boxes in the lower two thirds of the image."""
    width_px, height_px = image_size
    box_height = height * rng.uniform(0.6, 1.2, count)
    box_width = box_height * rng.uniform(0.3, 0.5, count)
    x = rng.uniform(0.05 * width_px, 0.95 * width_px - box_width)
    bottom = rng.uniform(height_px / 3 + box_height, height_px)
    bottom = np.maximum(bottom, box_height)
    return np.column_stack([x, bottom - box_height, x + box_width, bottom])


def _false_boxes(
    rng: np.random.Generator, model: DetectorModel, sites: np.ndarray, like: Detections,
    image_size: tuple[int, int], height: float,
) -> Detections:
    fire = rng.random(len(sites)) < model.false_site_rate
    boxes = sites[fire]
    boxes = boxes + 0.02 * (boxes[:, 3:4] - boxes[:, 1:2]) * rng.standard_normal(boxes.shape)
    transient = int(rng.poisson(model.transient_false))
    if transient:
        boxes = np.concatenate([boxes, _false_sites(rng, transient, image_size, height)])
    count = len(boxes)
    class_id = np.full(count, int(np.bincount(like.class_id).argmax()) if len(like) else 0,
                       np.int64)
    return Detections(xyxy=boxes, confidence=rng.uniform(0.3, 0.6, count), class_id=class_id,
                      object_id=np.full(count, -1, np.int64))
