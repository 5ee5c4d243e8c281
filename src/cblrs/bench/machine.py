"""What machine a benchmark ran on, and small timing helpers shared by the benchmarks."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np


def machine_info() -> dict[str, Any]:
    """CPU model, core count, OS, Python, numpy and OpenCV versions of this machine."""
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    cpu_model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.lower().startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return {
        "cpu": cpu_model,
        "cores": cores,
        "load_average_1min": round(load, 2),
        "system": f"{platform.system()} {platform.release()}",
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        # numpy's BLAS may use several threads for the homography's matrix products
        "thread_environment": {
            name: os.environ[name]
            for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
            if name in os.environ
        },
    }


def describe_machine(info: dict[str, Any]) -> str:
    """One line for the text output of a benchmark."""
    threads = ", ".join(
        f"{key}={value}" for key, value in info.get("thread_environment", {}).items()
    )
    return (
        f"machine: {info['cpu']}, {info['cores']} cores (load {info['load_average_1min']}), "
        f"{info['system']}, Python {info['python']}, numpy {info['numpy']}, "
        f"OpenCV {info['opencv']}" + (f", {threads}" if threads else "")
    )


def summarise(samples: list[float]) -> dict[str, float]:
    """Median, minimum and maximum of repeated measurements (seconds or any unit)."""
    if not samples:
        raise ValueError("no samples to summarise")
    return {
        "median": float(statistics.median(samples)),
        "min": float(min(samples)),
        "max": float(max(samples)),
        "repeats": len(samples),
    }


def time_call(function: Callable[[], object], repeats: int) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls of ``function`` (perf_counter)."""
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return samples


def json_ready(value: Any) -> Any:
    """A copy of nested dicts/lists with numpy scalars as Python numbers and NaN/inf as None."""
    if isinstance(value, dict):
        return {str(key): json_ready(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(item) for item in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
