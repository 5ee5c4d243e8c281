"""The report of ``cblrs bench mqtt``: the median of repeated runs, the machine the runs
ran on, and the results as a markdown table (the rows :mod:`cblrs.bench.mqtt` measures)."""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

WARM_UP_FRAMES = 10
"""Paced runs also report the subscriber's latency of the frames after each camera's first
this many: the ordering learns a camera's frame period from its first
``MINIMUM_INTERVALS + 1`` (4) frames (:mod:`cblrs.matching.timing`), and when it is not told
the cameras' frame rate (``--unknown-fps``) a frame's window waits for the camera's next
frame until then (a run of 10 s at 10 fps has 100 frames, so those few set its p99)."""


FIRST_FRAMES = 4
"""Paced runs also report the subscriber's slowest update of the frames captured in the first
this many frame periods: the frames the ordering sees before it has measured a camera's
period (``MINIMUM_INTERVALS + 1`` frames)."""


def median_of(runs: list[dict]) -> dict:
    """One row from repeated runs: the median of every float, the fewest messages received."""
    merged = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, float):
            merged[key] = statistics.median(run[key] for run in runs)
    merged["received"] = min(run["received"] for run in runs)
    merged["flushed"] = all(run["flushed"] for run in runs)
    merged["repeats"] = len(runs)
    return merged


def machine() -> dict:
    """CPU model, cores, Python, Mosquitto and paho-mqtt versions of this machine."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions: dict[str, str | None] = {}
    for package in ("paho-mqtt", "msgspec", "numpy"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    try:
        mosquitto = subprocess.run(
            ["mosquitto", "-h"], capture_output=True, text=True, timeout=10
        ).stdout.splitlines()[0]
    except (OSError, IndexError, subprocess.SubprocessError):
        mosquitto = None
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "mosquitto": mosquitto,
        **versions,
    }


def format_value(value: float, width: int = 7, digits: int = 1) -> str:
    return " " * (width - 1) + "-" if math.isnan(value) else f"{value:{width}.{digits}f}"


def markdown_table(info: dict, rows: list[dict], args: argparse.Namespace) -> str:
    """The results as a markdown table with the machine and settings above it."""

    def cell(value: float, digits: int = 1) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}f}"

    def pair(first: float, second: float) -> str:
        return "–" if math.isnan(first) else f"{cell(first)} / {cell(second)}"

    def tracked(row: dict) -> str:
        alone = row.get("tracker_alone_per_s")
        if alone is None or math.isnan(row["tracked_per_s"]):
            return cell(row["tracked_per_s"], 0)
        text = (
            f"{row['tracked_per_s']:.0f} ({100 * row['tracked_per_s'] / alone:.0f} % of {alone:.0f}"
        )
        wall = row.get("tracker_alone_wall_per_s")
        if wall is not None:
            text += f"; {100 * row['tracked_per_s'] / wall:.0f} % of {wall:.0f}"
        return text + ")"

    def subscriber(row: dict) -> str:
        text = pair(row["subscriber_p50_ms"], row["subscriber_p99_ms"])
        if not math.isnan(row.get("subscriber_steady_p50_ms", math.nan)):
            steady = pair(row["subscriber_steady_p50_ms"], row["subscriber_steady_p99_ms"])
            text += f" ({steady})"
        return text

    lines = [
        f"QoS 1 on loopback, {args.people} detections per message, {args.fps:g} fps when paced, "
        f"{args.matcher} matcher; publishers: {args.publisher} (one connection per camera, "
        f"other processes); {clocks_text(args)}. {info['cpu']}, {info['cores']} cores, "
        f"Python {info['python']}, "
        f"{info['mosquitto']}, paho-mqtt {info['paho-mqtt']}; "
        + ("Nagle's algorithm on (no TCP_NODELAY); " if args.nagle else "TCP_NODELAY on; ")
        + ("the matcher not told the cameras' frame rate (--unknown-fps); "
           if getattr(args, "unknown_fps", False) else "")
        + "load average "
        f"{info['load_start'][0]:.2f} at start, {info['load_end'][0]:.2f} at end (a shared "
        f"machine); medians of {args.repeats} runs.",
        "",
        "| cameras | receiver | rate | received msg/s | tracked msg/s (% of the tracker alone: "
        "msg per CPU s; msg/s in one process at the same load) "
        "| receipt p50 / p99 ms | track output p50 / p99 ms "
        f"| **tracks at a subscriber** p50 / p99 ms (after each camera's first {WARM_UP_FRAMES}"
        " frames) | lost |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['cameras']} | {row['receiver']} | {row['rate']} "
            f"| {row['received_per_s']:.0f} | {tracked(row)} "
            f"| {pair(row['receipt_p50_ms'], row['receipt_p99_ms'])} "
            f"| {pair(row['track_p50_ms'], row['track_p99_ms'])} "
            f"| {subscriber(row)} "
            f"| {row['messages'] - row['received']} |"
        )
    return "\n".join(lines)


def clocks_text(args: Any) -> str:
    """How the simulated cameras stamp their frames, in words."""
    spread, jitter = args.clock_spread_ms, args.clock_jitter_ms
    if not spread and not jitter:
        return "every camera stamps a frame with the same time (idealised clocks)"
    return f"camera clocks: offsets spread over {spread:g} ms, per-frame jitter {jitter:g} ms (sd)"
