"""Tracking from real images through a detector, next to tracking the annotated boxes.

For each detection source (the annotated boxes; the detector on the whole frame; the detector
with tiles from the reference image): the detector's recall against the annotated boxes
(IoU >= 0.5), its time per image, and the tracking scores of both matchers (the annotated
area's rule of :func:`cblrs.evaluate`).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.calibration import default_ground
from cblrs.datasets import load_scene
from cblrs.detectors import OnnxDetector, box_iou
from cblrs.detectors.offline import detect_scene
from cblrs.evaluation.metrics import evaluate
from cblrs.pipeline import render_scene_references, track_scene

SCORES = ("HOTA", "DetA", "AssA", "DetRe", "DetPr", "LocA", "MOTA", "IDF1")


HEIGHT_BINS = (0, 100, 150, 200, 300, 100_000)
"""Annotated box heights (pixels) for the recall-by-size table."""


def box_recall(
    truth: list[list[Any]], found: list[list[Any]], threshold: float = 0.5
) -> tuple[float, list[float | None]]:
    """Share of annotated boxes a found box overlaps with IoU >= ``threshold`` (one-to-one),
    overall and per annotated box height bin (:data:`HEIGHT_BINS`; None for an empty bin)."""
    # lazy: scipy.optimize takes ~0.3 s to import; only this path needs it
    from scipy.optimize import linear_sum_assignment

    heights: list[np.ndarray] = []
    hits: list[np.ndarray] = []
    for truth_row, found_row in zip(truth, found, strict=True):
        for expected, detections in zip(truth_row, found_row, strict=True):
            hit = np.zeros(len(expected), dtype=bool)
            if len(expected) and len(detections):
                iou = box_iou(expected.xyxy, detections.xyxy)
                rows, columns = linear_sum_assignment(-iou)
                hit[rows[iou[rows, columns] >= threshold]] = True
            heights.append(expected.xyxy[:, 3] - expected.xyxy[:, 1])
            hits.append(hit)
    height, hit = np.concatenate(heights), np.concatenate(hits)
    by_height: list[float | None] = []
    for low, high in itertools.pairwise(HEIGHT_BINS):
        rows = (height >= low) & (height < high)
        by_height.append(float(hit[rows].mean()) if rows.any() else None)
    return float(hit.mean()) if len(hit) else 0.0, by_height


def benchmark_detection(dataset: str | Path, model: str | Path) -> dict[str, Any]:
    """Track the data set from its annotated boxes and from its images, both tilings.

    Returns:
        Per source: recall, boxes per image, ms per image, and per matcher the scores.
    """

    scene = load_scene(dataset)
    references = render_scene_references(scene)
    area = default_ground(dataset)
    detector = OnnxDetector(model)
    sources: dict[str, Any] = {"annotated boxes": (scene, None)}
    for tiling in ("off", "auto"):
        run = detect_scene(scene, dataset, detector, references, tiling=tiling)
        sources[f"detector, tiling {tiling}"] = (run.scene, run)
    result: dict[str, Any] = {
        "dataset": str(dataset),
        "model": str(model),
        "frames": len(scene.frames),
        "cameras": len(scene.cameras),
        "machine": machine_info(),
        "sources": {},
    }
    for name, (detected, run) in sources.items():
        real = run is not None
        recall, by_height = box_recall(scene.detections, detected.detections)
        entry: dict[str, Any] = {
            "boxes_per_image": float(
                np.mean([len(d) for row in detected.detections for d in row])
            ),
            "recall": recall,
            "recall_by_height": by_height,
            "ms_per_image": run.ms_per_image if real else 0.0,
            "tiles": [plan.describe() for plan in run.plans] if real else [],
            "matchers": {},
        }
        for matcher in ("fusion", "paper"):
            tracks = track_scene(
                detected, matcher, references=references, drop_hidden_feet=real
            ).tracks
            metrics = evaluate(scene.ground_truth, tracks, area=area)
            details = metrics.details()
            entry["matchers"][matcher] = {
                **{key: details[key] for key in SCORES},
                "ids": metrics.num_predicted_ids,
                "true_ids": metrics.num_gt_ids,
            }
        result["sources"][name] = entry
    return json_ready(result)


def detection_report(result: dict[str, Any]) -> str:
    """Markdown: one row per source and matcher."""
    header = ["detections", "recall (IoU 0.5)", "ms / image", "matcher", *SCORES, "ids"]
    rows = []
    for name, entry in result["sources"].items():
        for matcher, scores in entry["matchers"].items():
            rows.append(
                [name, f"{100 * entry['recall']:.1f} %",
                 entry["ms_per_image"] if entry["ms_per_image"] else "-", matcher]
                + [scores[key] for key in SCORES]
                + [f"{scores['ids']} / {scores['true_ids']}"]
            )
    bins = [
        f"{low}-{high} px" if high < 100_000 else f">= {low} px"
        for low, high in itertools.pairwise(HEIGHT_BINS)
    ]
    size_rows = [
        [name] + [f"{100 * value:.0f} %" if value is not None else "-"
                  for value in entry["recall_by_height"]]
        for name, entry in result["sources"].items() if name != "annotated boxes"
    ]
    tiles: list[str] = next(
        (entry["tiles"] for name, entry in result["sources"].items() if "auto" in name), []
    )
    return "\n".join([
        f"### Tracking {Path(result['dataset']).name} from its images "
        f"({result['frames']} frames x {result['cameras']} cameras, "
        f"{Path(result['model']).name})",
        "",
        describe_machine(result["machine"]) + ".",
        "Recall: annotated boxes a detector box overlaps with IoU >= 0.5 (annotations include "
        "people hidden behind others, which no detector sees). Scores: `cblrs eval`'s "
        "protocol (predictions outside the annotated area that match nobody are not scored).",
        "Tiles per camera (auto): " + "; ".join(sorted(set(tiles))) + ".",
        "",
        markdown_table(header, rows),
        "",
        "Detector recall (IoU >= 0.5) by the annotated box's height:",
        "",
        markdown_table(["detections", *bins], size_rows),
    ])
