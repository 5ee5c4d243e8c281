"""The targeting experiment on data-set scenes: box bottom centre against geometric targeting.

* :func:`wildtrack_targeting`: the target's ground error on WILDTRACK's annotated boxes.
* :func:`tracking_effect`: HOTA & co of the default pipeline with either targeting, per scene.

Both add to the result of :func:`cblrs.experiments.targeting.run_targeting` (its ``wildtrack``
and ``tracking`` entries), which :func:`cblrs.experiments.targeting.targeting_report` reads.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.datasets import load_scene
from cblrs.evaluation import evaluate
from cblrs.experiments.targeting import _json_ready
from cblrs.geometric_targeting import DEFAULT_CLASS_SIZES, GeometricTargeter
from cblrs.pipeline import render_scene_references, track_scene
from cblrs.targeting import target_pixels


def wildtrack_targeting(
    root: str | Path, frame_step: int = 4, class_sizes: dict | None = None
) -> dict[str, Any]:
    """Target error on WILDTRACK's annotated boxes: bottom centre vs geometric targeting.

    Each annotated box (every ``frame_step``-th frame, all seven cameras) is targeted, the
    target's ground point computed through the camera, and its distance to the annotated
    position of the same person measured.

    Returns:
        JSON-ready dict: per camera and overall ``median_m`` and ``mean_m`` for
        ``bottom_centre`` and ``geometric``, and the box count.
    """

    sizes = (class_sizes or DEFAULT_CLASS_SIZES)["person"]
    scene = load_scene(root)
    truth = scene.ground_truth
    per_camera = {}
    errors: dict[str, list] = {"bottom_centre": [], "geometric": []}
    for camera_index, camera in enumerate(scene.cameras):
        boxes, positions = [], []
        for frame_index in range(0, len(scene.frames), frame_step):
            detections = scene.detections[frame_index][camera_index]
            rows = truth.frame == scene.frames[frame_index]
            by_id = dict(zip(truth.track_id[rows].tolist(), truth.world_xy[rows], strict=True))
            for row, identity in enumerate(detections.object_id.tolist()):
                if identity in by_id:
                    boxes.append(detections.xyxy[row])
                    positions.append(by_id[identity])
        if not boxes:
            continue
        boxes_array, positions_array = np.array(boxes), np.array(positions)
        bottom, _ = target_pixels(boxes_array, 0.5, 1.0)
        geometric, _ = GeometricTargeter(camera, {"person": sizes}).pixels_for(
            boxes_array, np.asarray(sizes)
        )
        entry: dict[str, Any] = {"boxes": len(boxes)}
        for name, pixels in (("bottom_centre", bottom), ("geometric", geometric)):
            ground, valid = camera.pixel_to_world(np.nan_to_num(pixels, nan=-1e6))
            distance = np.hypot(*(ground - positions_array).T)[valid]
            errors[name].append(distance)
            entry[name] = {
                "median_m": float(np.median(distance)),
                "mean_m": float(np.mean(distance)),
            }
        per_camera[camera.name] = entry
    overall = {
        name: {
            "median_m": float(np.median(np.concatenate(values))),
            "mean_m": float(np.mean(np.concatenate(values))),
        }
        for name, values in errors.items()
    }
    return _json_ready(
        {
            "frame_step": frame_step,
            "person_size_lwh_m": list(sizes),
            "cameras": per_camera,
            "overall": overall,
        }
    )


def tracking_effect(scenes: dict[str, Any]) -> dict[str, Any]:
    """HOTA & co of the default pipeline with box targeting against geometric targeting.

    Args:
        scenes: name -> :class:`cblrs.datasets.scene.Scene` (posed cameras).

    Returns:
        JSON-ready dict: per scene, per targeting mode, the metrics and tracking seconds.
    """

    output: dict[str, Any] = {}
    for name, scene in scenes.items():
        references = render_scene_references(scene)
        output[name] = {}
        vehicles = {name: size for name, size in DEFAULT_CLASS_SIZES.items() if name != "person"}
        modes: dict[str, Any] = {
            "box": "box",
            "geometric": "geometric",
            # people keep their foot point; only vehicles are fitted
            "geometric, vehicles only": [
                GeometricTargeter(camera, vehicles) for camera in scene.cameras
            ],
        }
        for targeting, option in modes.items():
            start = time.perf_counter()
            result = track_scene(scene, references=references, targeting=option)
            seconds = time.perf_counter() - start
            metrics = evaluate(scene.ground_truth, result.tracks).to_dict()
            output[name][targeting] = {**metrics, "seconds": seconds}
    return _json_ready(output)
