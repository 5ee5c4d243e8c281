"""The paper's Table I on this machine: pixel -> world lookup by homography, LUT and colour.

Each localiser is timed two ways on the same ``n`` random pixels (fixed seed):

* one point at a time: a plain Python loop calling ``locate_one(x, y)``, as the paper did;
* batched: one vectorised ``locate(pixels)`` call.

The file sizes of what each method stores (LUT as ``.npy`` float32, reference PNG 8 and 16
bit, homography JSON) and their in-memory sizes are reported for the same camera.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.cameras import BenchCamera, benchmark_camera
from cblrs.bench.machine import json_ready, machine_info, summarise, time_call
from cblrs.calibration import camera_to_dict
from cblrs.camera import Camera
from cblrs.locate import ColorLocator, HomographyLocator, LUTLocator
from cblrs.reference import render_reference

logger = logging.getLogger(__name__)

METHODS = ("homography", "lut", "colour")
EXTRA_ONE_POINT = "homography_numpy"

PAPER_DEVICE = "i5-4690K @ 3.50GHz"
PAPER_TABLE_I: dict[str, dict[str, float]] = {
    # seconds for n = 100000 one-point lookups (the paper's Table I)
    "i5-4690K @ 3.50GHz": {"homography": 0.84073, "lut": 0.24109, "colour": 0.19545},
    "Pi 3 @ 1.2GHz": {"homography": 30.7385, "lut": 10.2173, "colour": 8.40112},
    "Pi 4 @ 2GHz": {"homography": 19.16133, "lut": 5.80970, "colour": 4.59746},
    "Jetson Nano @ 1.6GHz": {"homography": 115.0698, "lut": 31.0034, "colour": 23.1562},
    "Jetson Xavier @ 2.2GHz": {"homography": 4.98495, "lut": 1.07157, "colour": 0.81251},
}
PAPER_N = 100_000
PAPER_SIZES_BYTES = {
    "lut": 31.6 * 2**20,  # "31.6 MiB"
    "png": 143.4 * 2**10,  # "143.4 KiB" (8 bit)
    "homography_json": 500,  # "about 500 Bytes"
}


def make_locators(bench: BenchCamera, bits: int) -> dict[str, Any]:
    """The three localisers for a camera and its ground plane (same bounds for all three)."""
    plane = bench.plane(bits)
    x0, y0 = plane.origin
    bounds = (x0, y0, x0 + plane.width, y0 + plane.length)
    reference = render_reference(bench.camera, plane)
    return {
        "homography": HomographyLocator.from_camera(bench.camera, bounds=bounds),
        "lut": LUTLocator.from_camera(bench.camera, bounds=bounds),
        "colour": ColorLocator(reference),
        "reference": reference,
    }


def random_pixels(image_size: tuple[int, int], count: int, seed: int) -> np.ndarray:
    """(count, 2) int64 random pixel centres of an image, reproducible for a seed."""
    generator = np.random.default_rng(seed)
    width, height = image_size
    return np.column_stack(
        [generator.integers(0, width, count), generator.integers(0, height, count)]
    )


class NumpyHomographyOnePoint:
    """One-point homography written the usual way: a numpy 3x3 product per call.

    :meth:`HomographyLocator.locate_one` unrolls the product into nine scalar multiply-adds;
    this variant shows what a per-point matrix-library call costs (likely what the paper
    timed as "homography calculation").
    """

    def __init__(self, homography: np.ndarray):
        self.inverse = np.linalg.inv(np.asarray(homography, dtype=np.float64))

    def locate_one(self, x: float, y: float) -> tuple[float, float] | None:
        world = self.inverse @ np.array([x, y, 1.0])
        if world[2] <= 0.0:
            return None
        return float(world[0] / world[2]), float(world[1] / world[2])


def _time_one_point(locator: Any, points: list[tuple[int, int]]) -> float:
    locate_one = locator.locate_one
    start = time.perf_counter()
    for x, y in points:
        locate_one(x, y)
    return time.perf_counter() - start


def file_sizes(bench: BenchCamera, reference_8: Any, reference_16: Any, lut: LUTLocator) -> dict:
    """Bytes on disk of what each method stores for the camera."""
    with tempfile.TemporaryDirectory() as folder:
        lut_bytes = lut.save(Path(folder) / "lut.npy").stat().st_size
    homography_only = Camera.from_homography(
        bench.camera.name, bench.camera.homography, bench.camera.image_size
    )
    return {
        "lut_npy_float32": lut_bytes,
        "png_8bit": len(reference_8.to_png_bytes()),
        "png_16bit": len(reference_16.to_png_bytes()),
        "homography_json": len(json.dumps(camera_to_dict(homography_only))),
        "full_calibration_json": len(json.dumps(camera_to_dict(bench.camera))),
    }


def benchmark_lookup(
    count: int = PAPER_N,
    repeats: int = 5,
    seed: int = 0,
    bits: int = 8,
    calibration: str | Path | None = None,
) -> dict[str, Any]:
    """Time the three localisers one point at a time and batched.

    Args:
        count: number of random pixels n.
        repeats: timed runs per method; medians, minima and maxima are reported.
        seed: random seed of the pixels.
        bits: bits per channel of the reference image the colour method reads.
        calibration: WILDTRACK folder (default: found automatically, else a built-in camera).

    Returns:
        A JSON-ready dict: ``machine``, ``camera``, ``one_point`` and ``batched`` (per method:
        seconds ``{median, min, max, repeats}`` and ns per point), ``ratios``, ``agreement``,
        ``sizes_bytes``, ``memory_bytes`` and the paper's figures.
    """
    if count <= 0 or repeats <= 0:
        raise ValueError("count and repeats must be positive")
    bench = benchmark_camera(calibration)
    locators = make_locators(bench, bits)
    other_bits = 16 if bits == 8 else 8
    other_reference = render_reference(bench.camera, bench.plane(other_bits))
    pixels = random_pixels(bench.camera.image_size, count, seed)
    points = [(int(x), int(y)) for x, y in pixels]
    pixels_float = pixels.astype(np.float64)

    one_point: dict[str, dict] = {}
    batched: dict[str, dict] = {}
    # Interleave the methods across repeats so background load hits all of them alike.
    one_samples: dict[str, list[float]] = {method: [] for method in METHODS}
    batch_samples: dict[str, list[float]] = {method: [] for method in METHODS}
    colour_read_samples: list[float] = []
    reference = locators["reference"]
    numpy_homography = NumpyHomographyOnePoint(bench.camera.homography)
    one_samples[EXTRA_ONE_POINT] = []
    for _ in range(repeats):
        for method in METHODS:
            one_samples[method].append(_time_one_point(locators[method], points))
            batch_samples[method] += time_call(partial(locators[method].locate, pixels_float), 1)
        colour_read_samples += time_call(lambda: reference.colours_at(pixels_float), 1)
        one_samples[EXTRA_ONE_POINT].append(_time_one_point(numpy_homography, points))
    for method in (*METHODS, EXTRA_ONE_POINT):
        one_point[method] = summarise(one_samples[method])
        one_point[method]["ns_per_point"] = one_point[method]["median"] / count * 1e9
    for method in METHODS:
        batched[method] = summarise(batch_samples[method])
        batched[method]["ns_per_point"] = batched[method]["median"] / count * 1e9
    batched["colour_read_only"] = summarise(colour_read_samples)
    batched["colour_read_only"]["ns_per_point"] = (
        batched["colour_read_only"]["median"] / count * 1e9
    )

    results = {method: locators[method].locate(pixels_float) for method in METHODS}
    both = results["homography"][1] & results["colour"][1]
    gap = np.hypot(*(results["homography"][0][both] - results["colour"][0][both]).T)
    agreement = {
        "valid_fraction": {method: float(results[method][1].mean()) for method in METHODS},
        "colour_vs_homography_max_m": float(gap.max()) if gap.size else float("nan"),
        # a colour decodes to its cell centre: at most half a step off along x and along y
        "half_cell_diagonal_m": float(np.hypot(*bench.plane(bits).step) / 2.0),
    }
    reference_8 = reference if bits == 8 else other_reference
    reference_16 = other_reference if bits == 8 else reference
    lut = locators["lut"]
    paper = PAPER_TABLE_I[PAPER_DEVICE]
    return json_ready(
        {
            "machine": machine_info(),
            "camera": {
                "source": bench.source,
                "name": bench.camera.name,
                "image_size": list(bench.camera.image_size),
                "ground": list(bench.ground),
                "bits": bits,
                "step_m": list(bench.plane(bits).step),
            },
            "n": count,
            "seed": seed,
            "one_point": one_point,
            "batched": batched,
            "ratios": {
                "one_point_colour_over_homography": (
                    one_point["colour"]["median"] / one_point["homography"]["median"]
                ),
                "one_point_lut_over_homography": (
                    one_point["lut"]["median"] / one_point["homography"]["median"]
                ),
                "one_point_colour_over_lut": one_point["colour"]["median"]
                / one_point["lut"]["median"],
                "one_point_colour_over_homography_numpy": (
                    one_point["colour"]["median"] / one_point[EXTRA_ONE_POINT]["median"]
                ),
                "batched_colour_over_homography": (
                    batched["colour"]["median"] / batched["homography"]["median"]
                ),
                "batched_lut_over_homography": batched["lut"]["median"]
                / batched["homography"]["median"],
                "paper_colour_over_homography": paper["colour"] / paper["homography"],
                "paper_lut_over_homography": paper["lut"] / paper["homography"],
                "paper_colour_over_lut": paper["colour"] / paper["lut"],
            },
            "agreement": agreement,
            "sizes_bytes": file_sizes(bench, reference_8, reference_16, lut),
            "memory_bytes": {
                "lut_table": int(lut.table.nbytes),
                "reference_pixels_8bit": int(reference_8.pixels.nbytes),
                "reference_pixels_16bit": int(reference_16.pixels.nbytes),
                "colour_packed_index": int(reference.packed.nbytes),
                "homography": 9 * 8,
            },
            "paper": {
                "device": PAPER_DEVICE,
                "n": PAPER_N,
                "table_i_seconds": PAPER_TABLE_I,
                "sizes_bytes": PAPER_SIZES_BYTES,
            },
        }
    )
