"""Tracker throughput against live tracks and cameras (wraps :mod:`cblrs.bench.tracker_load`).

Only ``matcher.update`` is timed, on pre-built messages of a synthetic crowd (see
:func:`cblrs.bench.tracker_load.measure_throughput`); medians over repeats, one core. Each
figure is given in wall time and in the process's CPU time: on a machine shared with other
jobs the wall figures measure the load as much as the tracker, the CPU ones the tracker's
work (the table's "CPU share" says how much of the wall time the process had a core).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.bench.tracker_load import measure_throughput

DEFAULT_TRACKS = (25, 50, 100, 200, 400)
DEFAULT_CAMERAS = (1, 4, 8)
DEFAULT_MATCHERS = ("fusion", "paper")


def benchmark_tracker(
    tracks: tuple[int, ...] = DEFAULT_TRACKS,
    cameras: tuple[int, ...] = DEFAULT_CAMERAS,
    matchers: tuple[str, ...] = DEFAULT_MATCHERS,
    frames: int = 30,
    repeats: int = 3,
) -> dict[str, Any]:
    """Detections per second for every (matcher, live tracks, cameras) combination.

    Returns:
        JSON-ready dict with ``machine`` and ``rows`` (the measurement dicts of
        :func:`measure_throughput`).
    """
    if frames <= 0 or repeats <= 0:
        raise ValueError("frames and repeats must be positive")
    rows = [
        measure_throughput(count, camera_count, frames=frames, matcher=matcher, repeats=repeats)
        for matcher in matchers
        for camera_count in cameras
        for count in tracks
    ]
    return json_ready(
        {"machine": machine_info(), "frames": frames, "repeats": repeats, "rows": rows}
    )


def tracker_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_tracker`'s result."""

    return "\n".join(
        [
            f"### Tracker throughput (matcher.update only, {result['frames']} frames, median of "
            f"{result['repeats']} runs; wall and process CPU time)",
            "",
            describe_machine(result["machine"]),
            "",
            markdown_table(
                [
                    "matcher",
                    "cameras",
                    "live tracks",
                    "detections/frame",
                    "ms/frame",
                    "detections/s",
                    "CPU ms/frame",
                    "CPU µs/detection",
                    "CPU share",
                ],
                [
                    [
                        row["matcher"],
                        row["cameras"],
                        row["live_tracks"],
                        row["detections_per_frame"],
                        row["milliseconds_per_frame"],
                        round(row["detections_per_second"]),
                        row["cpu_milliseconds_per_frame"],
                        row["cpu_microseconds_per_detection"],
                        round(row["cpu_share"], 2),
                    ]
                    for row in result["rows"]
                ],
            ),
        ]
    )


def plot_tracker(result: dict[str, Any], out: str | Path) -> Path:
    """Detections/s and ms/frame against live tracks, one line per matcher and camera count."""
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figure, axes = plt.subplots(1, 2, figsize=(9.5, 3.6))
    matchers = sorted({row["matcher"] for row in result["rows"]})
    cameras = sorted({row["cameras"] for row in result["rows"]})
    for matcher_index, matcher in enumerate(matchers):
        for camera_index, camera_count in enumerate(cameras):
            rows = sorted(
                (
                    row
                    for row in result["rows"]
                    if row["matcher"] == matcher and row["cameras"] == camera_count
                ),
                key=lambda row: row["live_tracks"],
            )
            style = dict(
                color=f"C{camera_index}",
                marker="os"[matcher_index % 2],
                linestyle="-" if matcher_index == 0 else "--",
                label=f"{matcher}, {camera_count} camera{'s' if camera_count > 1 else ''}",
            )
            tracks = [row["live_tracks"] for row in rows]
            axes[0].plot(tracks, [row["detections_per_second"] for row in rows], **style)
            axes[1].plot(tracks, [row["milliseconds_per_frame"] for row in rows], **style)
    axes[0].set_ylabel("detections per second")
    axes[1].set_ylabel("milliseconds per frame")
    ticks = sorted({row["live_tracks"] for row in result["rows"]})
    for axis in axes:
        axis.set_xlabel("live tracks")
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xticks(ticks, [str(tick) for tick in ticks])
        axis.minorticks_off()
        axis.grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=7)
    figure.suptitle("Tracker cost against live tracks and cameras (one core)")
    figure.tight_layout()
    path = out / "tracker_throughput.png"
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return path
