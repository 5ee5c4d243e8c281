"""End-to-end WILDTRACK timing: load, render, track, evaluate; and the memory peak.

Times are medians over repeats. The memory figures come from a separate, untimed pass:
``tracemalloc`` (peak of Python and numpy allocations during render + track + evaluate) and
the process's maximum resident set size (``resource.getrusage``, includes the interpreter,
libraries and everything run before).
"""

from __future__ import annotations

import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.datasets import load_scene
from cblrs.evaluation import evaluate
from cblrs.pipeline import render_scene_references, track_scene


def _max_rss_bytes() -> int | None:
    usage = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(usage if sys.platform == "darwin" else usage * 1024)


def benchmark_pipeline(
    root: str | Path, repeats: int = 3, targetings: tuple[str, ...] = ("box", "geometric")
) -> dict[str, Any]:
    """Time the whole WILDTRACK pipeline.

    Args:
        root: the WILDTRACK folder.
        repeats: timed runs (the geometric targeting variant runs once: it is slow).
        targetings: targeting modes to time (``"box"``, ``"geometric"``).

    Returns:
        JSON-ready dict: ``stages`` (seconds per stage, median), ``metrics`` per targeting,
        ``memory`` (tracemalloc peak and max RSS in bytes), ``detections``, ``frames``.
    """

    if repeats <= 0:
        raise ValueError("repeats must be positive")
    loads, renders, tracks, evaluations = [], [], [], []
    metrics: dict[str, Any] = {}
    scene = None
    for _ in range(repeats):
        start = time.perf_counter()
        scene = load_scene(root)
        loads.append(time.perf_counter() - start)
        start = time.perf_counter()
        references = render_scene_references(scene)
        renders.append(time.perf_counter() - start)
        start = time.perf_counter()
        result = track_scene(scene, references=references)
        tracks.append(time.perf_counter() - start)
        start = time.perf_counter()
        metrics["box"] = evaluate(scene.ground_truth, result.tracks).to_dict()
        evaluations.append(time.perf_counter() - start)
    assert scene is not None
    detections = sum(len(boxes) for per_camera in scene.detections for boxes in per_camera)
    stages = {
        "load": statistics.median(loads),
        "render": statistics.median(renders),
        "track": statistics.median(tracks),
        "evaluate": statistics.median(evaluations),
    }
    extra: dict[str, float] = {}
    for targeting in targetings:
        if targeting == "box":
            continue
        start = time.perf_counter()
        result = track_scene(scene, references=references, targeting=targeting)
        extra[f"track ({targeting} targeting)"] = time.perf_counter() - start
        metrics[targeting] = evaluate(scene.ground_truth, result.tracks).to_dict()

    tracemalloc.start()
    scene = load_scene(root)
    references = render_scene_references(scene)
    result = track_scene(scene, references=references)
    evaluate(scene.ground_truth, result.tracks)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return json_ready(
        {
            "machine": machine_info(),
            "dataset": str(root),
            "frames": len(scene.frames),
            "cameras": len(scene.cameras),
            "detections": detections,
            "repeats": repeats,
            "stages_seconds": stages,
            "total_seconds": sum(stages.values()),
            "extra_seconds": extra,
            "detections_per_second_tracking": detections / stages["track"],
            "metrics": metrics,
            "memory": {"tracemalloc_peak_bytes": peak, "max_rss_bytes": _max_rss_bytes()},
        }
    )


def pipeline_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_pipeline`'s result."""

    stages = result["stages_seconds"]
    rows = [[stage, seconds] for stage, seconds in stages.items()]
    rows.append(["total (load + render + track + evaluate)", result["total_seconds"]])
    rows += [[name, seconds] for name, seconds in result["extra_seconds"].items()]
    memory = result["memory"]
    return "\n".join(
        [
            f"### End-to-end WILDTRACK ({result['frames']} frames, {result['cameras']} cameras, "
            f"{result['detections']:,} boxes; median of {result['repeats']} runs)",
            "",
            describe_machine(result["machine"]),
            "",
            markdown_table(["stage", "seconds"], rows),
            "",
            f"Tracking throughput (messages + matcher): "
            f"{result['detections_per_second_tracking']:,.0f} detections/s. Memory: tracemalloc "
            f"peak {memory['tracemalloc_peak_bytes'] / 2**20:.1f} MiB during one pass; max RSS "
            f"{(memory['max_rss_bytes'] or 0) / 2**20:.0f} MiB.",
            "",
            markdown_table(
                ["targeting", "HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1"],
                [
                    [
                        name,
                        values["HOTA"],
                        values["DetA"],
                        values["AssA"],
                        values["LocA"],
                        values["MOTA"],
                        values["IDF1"],
                    ]
                    for name, values in result["metrics"].items()
                ],
            ),
        ]
    )
