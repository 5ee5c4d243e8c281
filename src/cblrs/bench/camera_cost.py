"""On-camera cost per frame on real frames: decode, detector, targeting + colour lookup, encode.

The paper's edge-device argument, measured honestly: what a camera spends per 1920 x 1080
frame of MultiviewX with the shipped YOLOX-Nano, whole frame and tiled, and which share of it
the colour lookup (the method's own step) is.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.datasets import load_scene
from cblrs.datasets.images import read_image, scene_image_paths
from cblrs.detectors import OnnxDetector, TiledDetector, plan_tiles, whole_frame_plan
from cblrs.edge import make_message
from cblrs.pipeline import render_scene_references
from cblrs.runtime.wire import encode_message
from cblrs.targeting import target_pixels


def benchmark_camera(
    dataset: str | Path, model: str | Path, repeats: int = 3, frames: int = 2
) -> dict[str, Any]:
    """Time every stage of the camera step on the data set's real frames.

    Args:
        dataset: a WILDTRACK / MultiviewX folder with images (``Image_subsets/C<k>/``).
        model: the ONNX detector.
        repeats: timed runs of each stage per image (the median is reported).
        frames: how many of the data set's frames (all cameras) to time.

    Returns:
        Per stage the median milliseconds per frame (and microseconds per detection for the
        per-detection stages), for the whole frame and for the tiled detector.
    """
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    scene = load_scene(dataset)
    last = int(scene.frames[min(frames, len(scene.frames)) - 1])
    scene = scene.select_frames(int(scene.frames[0]), last)
    references = render_scene_references(scene)
    paths = scene_image_paths(dataset, len(scene.cameras), scene.frames)
    detector = OnnxDetector(model)
    canvas = np.full((detector.input_size[1], detector.input_size[0], 3), 114, np.uint8)
    plans = {
        "whole frame": [whole_frame_plan(r.image_size, detector.input_size) for r in references],
        "tiled": [plan_tiles(r, detector.input_size) for r in references],
    }

    def median_ms(function, count: int = repeats) -> float:
        samples = []
        for _ in range(count):
            started = time.perf_counter()
            function()
            samples.append(time.perf_counter() - started)
        return 1000.0 * statistics.median(samples)

    model_ms = median_ms(lambda: detector.candidates(canvas), max(repeats, 5))
    rows: dict[str, dict[str, list[float]]] = {mode: {} for mode in plans}
    detections_per_frame: dict[str, list[int]] = {mode: [] for mode in plans}
    tiles: dict[str, list[int]] = {mode: [] for mode in plans}
    for frame_paths in paths:
        for camera, (path, reference) in enumerate(zip(frame_paths, references, strict=True)):
            decode = median_ms(lambda path=path: cv2.imread(str(path), cv2.IMREAD_COLOR))
            image = read_image(path)
            for mode, camera_plans in plans.items():
                tiled = TiledDetector(detector, camera_plans[camera])
                found = tiled.detect(image)
                count = max(len(found), 1)
                pixels, _ = target_pixels(found.xyxy, 0.5, 1.0, reference.image_size)
                stages = rows[mode]
                stages.setdefault("decode", []).append(decode)
                stages.setdefault("detect", []).append(
                    median_ms(lambda tiled=tiled, image=image: tiled.detect(image))
                )
                message = make_message("c", 0, 0.0, 0, found, reference, drop_hidden_feet=True)
                targeting = median_ms(
                    lambda found=found, reference=reference: make_message(
                        "c", 0, 0.0, 0, found, reference, drop_hidden_feet=True
                    ),
                    max(repeats, 20),
                )
                lookup = median_ms(
                    lambda reference=reference, pixels=pixels: reference.colours_at(pixels),
                    max(repeats, 20),
                )
                stages.setdefault("targeting + lookup", []).append(targeting)
                stages.setdefault("lookup alone", []).append(lookup)
                stages.setdefault("targeting per detection", []).append(targeting / count)
                stages.setdefault("lookup per detection", []).append(lookup / count)
                stages.setdefault("encode", []).append(
                    median_ms(lambda message=message: encode_message(message, 1), max(repeats, 20))
                )
                detections_per_frame[mode].append(len(found))
                tiles[mode].append(len(camera_plans[camera]))
    result: dict[str, Any] = {
        "dataset": str(dataset),
        "model": str(model),
        "model_input": list(detector.input_size),
        "images": len(paths) * len(scene.cameras),
        "repeats": repeats,
        "model_ms_at_input_size": model_ms,
        "machine": machine_info(),
        "modes": {},
    }
    for mode, stages in rows.items():
        medians = {name: float(np.median(values)) for name, values in stages.items()}
        step = sum(medians[key] for key in ("decode", "detect", "targeting + lookup", "encode"))
        result["modes"][mode] = {
            "ms": medians,
            "camera_step_ms": step,
            "lookup_share": medians["lookup alone"] / step,
            "detections_per_frame": float(np.median(detections_per_frame[mode])),
            "inferences_per_frame": float(np.median(tiles[mode])),
        }
    return json_ready(result)


def camera_report(result: dict[str, Any]) -> str:
    """Markdown: per stage, whole frame vs tiled."""

    modes = list(result["modes"])
    header = ["stage"] + [f"{mode}" for mode in modes]
    labels = [
        ("decode", "decode JPEG 1920x1080 (ms/frame)", 1.0),
        ("detect", "detector (ms/frame)", 1.0),
        ("targeting + lookup", "targeting + colour lookup (ms/frame)", 1.0),
        ("targeting per detection", "  per detection (µs)", 1000.0),
        ("lookup alone", "colour lookup alone (ms/frame)", 1.0),
        ("lookup per detection", "  per detection (µs)", 1000.0),
        ("encode", "message encode (ms/frame)", 1.0),
    ]
    rows = []
    for key, label, factor in labels:
        rows.append([label] + [result["modes"][mode]["ms"][key] * factor for mode in modes])
    rows.append(["camera step: all of the above (ms/frame)"]
                + [result["modes"][mode]["camera_step_ms"] for mode in modes])
    rows.append(["share of the colour lookup in the step"]
                + [f"{100 * result['modes'][mode]['lookup_share']:.3f} %" for mode in modes])
    rows.append(["model inferences per frame"]
                + [result["modes"][mode]["inferences_per_frame"] for mode in modes])
    rows.append(["detections per frame"]
                + [result["modes"][mode]["detections_per_frame"] for mode in modes])
    width, height = result["model_input"]
    return "\n".join([
        f"### On-camera cost per frame ({result['images']} real MultiviewX frames, "
        f"{Path(result['model']).name} at {width}x{height})",
        "",
        describe_machine(result["machine"]) + f"; medians of {result['repeats']}+ runs per image, "
        "then the median over the images.",
        f"The model alone at its input size: {result['model_ms_at_input_size']:.1f} ms "
        "per inference (onnxruntime, CPU).",
        "",
        markdown_table(header, rows),
    ])
