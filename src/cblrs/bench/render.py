"""Reference rendering time for a 1080p camera: 8 and 16 bit, with and without lens distortion.

"Cold" is the first render of a configuration with a freshly read camera (it includes
first-touch page faults of fresh arrays and, for a distorted camera, computing the inverse
lens map, which the camera then caches); "warm" is the median of the following calls.
Saving (PNG encode) and loading (PNG decode and validation) are timed as well, and building
the LUT, the alternative the paper compares with.
"""

from __future__ import annotations

import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

from cblrs.bench.cameras import benchmark_camera
from cblrs.bench.machine import json_ready, machine_info, summarise, time_call
from cblrs.locate import LUTLocator
from cblrs.reference import ReferenceImage, render_reference

TARGET_MS = 100.0


def benchmark_render(repeats: int = 5, calibration: str | Path | None = None) -> dict[str, Any]:
    """Render, save and load times of a 1080p reference, per bit depth and lens model.

    Args:
        repeats: warm runs per configuration (after one cold run).
        calibration: WILDTRACK folder (default: found automatically, else a built-in camera).

    Returns:
        A JSON-ready dict with ``machine``, ``camera`` and ``rows``; each row has ``bits``,
        ``distorted`` and millisecond figures ``cold_ms``, ``warm_ms`` (median, min, max),
        ``save_ms``, ``load_ms``, ``lut_build_ms`` and ``png_bytes``.
    """
    if repeats <= 0:
        raise ValueError("repeats must be positive")
    rows = []
    source = ""
    for distorted in (False, True):
        bench = benchmark_camera(calibration, distorted=distorted)
        source = bench.source
        for bits in (8, 16):
            plane = bench.plane(bits)
            start = time.perf_counter()
            reference = render_reference(bench.camera, plane)
            cold = time.perf_counter() - start
            warm = time_call(partial(render_reference, bench.camera, plane), repeats)
            with tempfile.TemporaryDirectory() as folder:
                path = Path(folder) / "reference.png"
                save = time_call(partial(reference.save, path), repeats)
                load = time_call(partial(ReferenceImage.load, path), repeats)
                png_bytes = path.stat().st_size
            lut = time_call(partial(LUTLocator.from_camera, bench.camera), max(1, repeats // 2))
            rows.append(
                {
                    "bits": bits,
                    "distorted": distorted,
                    "camera": bench.camera.name,
                    "cold_ms": cold * 1e3,
                    "warm_ms": _milliseconds(summarise(warm)),
                    "save_ms": _milliseconds(summarise(save)),
                    "load_ms": _milliseconds(summarise(load)),
                    "lut_build_ms": _milliseconds(summarise(lut)),
                    "png_bytes": png_bytes,
                    "coverage": reference.coverage(),
                    "meets_target": summarise(warm)["median"] * 1e3 < TARGET_MS,
                }
            )
    return json_ready(
        {
            "machine": machine_info(),
            "camera": {"source": source, "image_size": [1920, 1080]},
            "target_ms": TARGET_MS,
            "repeats": repeats,
            "rows": rows,
        }
    )


def _milliseconds(summary: dict[str, float]) -> dict[str, float]:
    return {key: (value * 1e3 if key != "repeats" else value) for key, value in summary.items()}
