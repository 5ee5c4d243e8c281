"""Where the reference image wins even when a batched homography is as fast: measured claims.

1. **Lens distortion.** A plain homography ignores the lens; the reference image is rendered
   for the raw frame. Error of each method on a distorted camera against the exact ray-plane
   intersection, in centimetres, and the cost of doing it exactly with maths instead
   (undistortion plus homography) on the camera.
2. **Non-planar ground.** Terraces at several heights, and a ramp approximated by strips:
   homography-on-one-plane error against the colour lookup's.
3. **Several planes (B channel).** A footbridge above the ground seen by one camera, and two
   areas 1 km apart: one plane spanning both against one plane each.
4. **What the camera holds and computes.** Per method: stored bytes, memory, ns per point,
   and whether the camera needs its calibration.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.bench.cameras import benchmark_camera, synthetic_camera
from cblrs.bench.machine import json_ready, machine_info, summarise
from cblrs.bench.report import markdown_table
from cblrs.calibration import camera_to_dict
from cblrs.camera import Camera
from cblrs.locate import ColorLocator, HomographyLocator, LUTLocator
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference

FloatArray = NDArray[np.float64]


def _error_stats(estimate: FloatArray, truth: FloatArray, valid: NDArray[np.bool_]) -> dict:
    """Median, 95th percentile and maximum error in centimetres over rows valid in both."""
    usable = valid & np.isfinite(estimate).all(axis=1) & np.isfinite(truth).all(axis=1)
    error = np.hypot(*(estimate[usable] - truth[usable]).T) * 100.0
    if error.size == 0:
        return {"median_cm": None, "p95_cm": None, "max_cm": None, "points": 0}
    return {
        "median_cm": float(np.median(error)),
        "p95_cm": float(np.percentile(error, 95)),
        "max_cm": float(error.max()),
        "points": int(error.size),
    }


def _median_ns(function, count: int, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return summarise(samples)["median"] / max(count, 1) * 1e9


def _pixels(camera: Camera, count: int, seed: int) -> FloatArray:
    generator = np.random.default_rng(seed)
    width, height = camera.image_size
    return np.column_stack(
        [generator.integers(0, width, count), generator.integers(0, height, count)]
    ).astype(np.float64)


# ---------------------------------------------------------------------- 1. distortion
def distortion_claim(
    count: int, repeats: int, seed: int, calibration: str | Path | None
) -> dict[str, Any]:
    """Localisation error on a distorted camera, and the cost of exact maths on the camera."""
    bench = benchmark_camera(calibration, distorted=True)
    camera = bench.camera
    pixels = _pixels(camera, count, seed)
    x0, y0, width, length = bench.ground
    bounds = (x0, y0, x0 + width, y0 + length)
    truth, valid = camera.pixel_to_world(pixels)
    with np.errstate(invalid="ignore"):
        valid &= (
            (truth[:, 0] >= x0)
            & (truth[:, 0] <= x0 + width)
            & (truth[:, 1] >= y0)
            & (truth[:, 1] <= y0 + length)
        )
    homography = HomographyLocator.from_camera(camera, bounds=None)
    errors: dict[str, Any] = {}
    plain, _ = homography.locate(pixels)
    errors["homography (ignores the lens)"] = _error_stats(plain, truth, valid)
    lut = LUTLocator.from_camera(camera, bounds=bounds)
    errors["LUT (float32)"] = _error_stats(lut.locate(pixels)[0], truth, valid)
    locators = {}
    for bits in (8, 16):
        locators[bits] = ColorLocator(render_reference(camera, bench.plane(bits)))
        located, _ = locators[bits].locate(pixels)
        errors[f"colour, {bits} bit"] = _error_stats(located, truth, valid)
    reference = locators[8].reference
    timing = {
        "homography_plain_ns": _median_ns(lambda: homography.locate(pixels), count, repeats),
        "undistort_then_homography_ns": _median_ns(
            lambda: camera.pixel_to_world(pixels), count, repeats
        ),
        "colour_read_ns": _median_ns(lambda: reference.colours_at(pixels), count, repeats),
        "colour_locate_ns": _median_ns(lambda: locators[8].locate(pixels), count, repeats),
    }
    return {
        "camera": bench.source,
        "distortion": camera.distortion.tolist(),
        "steps_m": {bits: list(bench.plane(bits).step) for bits in (8, 16)},
        "errors": errors,
        "timing": timing,
    }


# ---------------------------------------------------------------------- 2. non-planar ground
def _nearest_plane_truth(
    camera: Camera,
    pixels: FloatArray,
    regions: list[tuple[float, tuple[float, float, float, float]]],
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.int64]]:
    """Exact ground point of each pixel on the nearest of several bounded horizontal planes.

    Args:
        regions: (height, (x0, y0, x1, y1)) per plane.

    Returns:
        ``(world_xy, valid, index)``: the hit point, whether any plane is hit, which plane.
    """
    centre = camera.centre
    best_depth = np.full(len(pixels), np.inf)
    world = np.full((len(pixels), 2), np.nan)
    index = np.full(len(pixels), -1)
    for number, (height, (x0, y0, x1, y1)) in enumerate(regions):
        hit, valid = camera.pixel_to_world(pixels, height_m=height)
        with np.errstate(invalid="ignore"):
            valid &= (hit[:, 0] >= x0) & (hit[:, 0] <= x1) & (hit[:, 1] >= y0) & (hit[:, 1] <= y1)
        depth = np.where(
            valid,
            np.linalg.norm(np.column_stack([hit, np.full(len(hit), height)]) - centre, axis=1),
            np.inf,
        )
        nearer = depth < best_depth
        best_depth[nearer] = depth[nearer]
        world[nearer] = hit[nearer]
        index[nearer] = number
    return world, np.isfinite(best_depth), index


def _ramp_truth(
    camera: Camera, pixels: FloatArray, start_y: float, end_y: float, rise_m: float, x_range
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Exact intersection with ground z=0 (y < start), a ramp, and a top z=rise (y > end)."""
    undistorted = camera.undistort_pixels(pixels)
    assert camera.intrinsics is not None and camera.rotation is not None
    rays = np.column_stack([undistorted, np.ones(len(pixels))]) @ np.linalg.inv(camera.intrinsics).T
    directions = rays @ camera.rotation  # camera -> world: R^T d, written row-wise
    directions[:, 2] *= camera.height_axis  # (x, y, height), as camera.centre
    centre = camera.centre
    slope = rise_m / (end_y - start_y)
    candidates = []
    with np.errstate(divide="ignore", invalid="ignore"):
        # ground, ramp, top: z = a + b * y  ->  cz + t dz = a + b (cy + t dy)
        for offset, gradient, low, high in (
            (0.0, 0.0, -np.inf, start_y),
            (-slope * start_y, slope, start_y, end_y),
            (rise_m, 0.0, end_y, np.inf),
        ):
            t = (offset + gradient * centre[1] - centre[2]) / (
                directions[:, 2] - gradient * directions[:, 1]
            )
            point = centre + t[:, None] * directions
            ok = (t > 0) & (point[:, 1] >= low) & (point[:, 1] <= high)
            ok &= (point[:, 0] >= x_range[0]) & (point[:, 0] <= x_range[1])
            candidates.append(np.where(ok, t, np.inf))
    distance = np.stack(candidates, axis=1)
    best = np.min(distance, axis=1)
    valid = np.isfinite(best)
    world = centre[:2] + np.where(valid, best, np.nan)[:, None] * directions[:, :2]
    return world, valid


def non_planar_claim(count: int, seed: int) -> dict[str, Any]:
    """Terraces and a ramp: homography on the ground plane against the colour lookup."""
    camera = synthetic_camera()
    pixels = _pixels(camera, count, seed)
    x_range = (-25.0, 25.0)
    # Terraces: three levels rising away from the camera.
    levels = [(0.0, 0.0, 15.0), (0.5, 15.0, 25.0), (1.0, 25.0, 50.0)]
    regions = [(height, (x_range[0], y0, x_range[1], y1)) for height, y0, y1 in levels]
    planes = PlaneSet(
        [
            PlaneSpec(
                number + 1,
                (x_range[0], y0),
                x_range[1] - x_range[0],
                y1 - y0,
                bits=16,
                height=height,
            )
            for number, (height, y0, y1) in enumerate(levels)
        ]
    )
    truth, valid, level = _nearest_plane_truth(camera, pixels, regions)
    colour, colour_valid = ColorLocator(render_reference(camera, planes)).locate(pixels)
    flat, _ = HomographyLocator.from_camera(camera).locate(pixels)
    terraces = {}
    for number, (height, _, _) in enumerate(levels):
        rows = valid & (level == number)
        terraces[f"{height:g} m"] = {
            "homography_z0": _error_stats(flat, truth, rows),
            "colour_16bit": _error_stats(colour, truth, rows & colour_valid),
        }
    # Ramp: 2 m rise over 20 m (10 %), approximated by horizontal strips in the reference.
    start_y, end_y, rise = 15.0, 35.0, 2.0
    ramp_truth, ramp_valid = _ramp_truth(camera, pixels, start_y, end_y, rise, x_range)
    on_ramp = ramp_valid & (ramp_truth[:, 1] > start_y) & (ramp_truth[:, 1] < end_y)
    ramp = {"homography_z0": _error_stats(flat, ramp_truth, on_ramp)}
    for strips in (1, 5, 20, 80):
        edges = np.linspace(start_y, end_y, strips + 1)
        specs = [PlaneSpec(1, (x_range[0], 0.0), 50.0, start_y, bits=16, height=0.0)]
        for number in range(strips):
            middle = (edges[number] + edges[number + 1]) / 2
            specs.append(
                PlaneSpec(
                    number + 2,
                    (x_range[0], edges[number]),
                    50.0,
                    edges[number + 1] - edges[number],
                    bits=16,
                    height=rise * (middle - start_y) / (end_y - start_y),
                )
            )
        specs.append(
            PlaneSpec(strips + 2, (x_range[0], end_y), 50.0, 50.0 - end_y, bits=16, height=rise)
        )
        located, located_valid = ColorLocator(render_reference(camera, specs)).locate(pixels)
        ramp[f"colour_16bit_{strips}_strips"] = _error_stats(
            located, ramp_truth, on_ramp & located_valid
        )
    return {
        "camera": "built-in synthetic (10 m high, 30 deg tilt)",
        "terraces": terraces,
        "ramp": {"rise_m": rise, "from_y_m": start_y, "to_y_m": end_y, "errors": ramp},
    }


# ---------------------------------------------------------------------- 3. several planes
def several_planes_claim(count: int, seed: int) -> dict[str, Any]:
    """A footbridge over the ground (levels told apart by B), and two distant areas."""
    camera = synthetic_camera()
    pixels = _pixels(camera, count, seed)
    bridge_height = 5.0
    regions = [(0.0, (-25.0, 0.0, 25.0, 50.0)), (bridge_height, (-25.0, 20.0, 25.0, 23.0))]
    planes = PlaneSet(
        [
            PlaneSpec(1, (-25.0, 0.0), 50.0, 50.0, bits=16, name="ground"),
            PlaneSpec(2, (-25.0, 20.0), 50.0, 3.0, bits=16, height=bridge_height, name="bridge"),
        ]
    )
    truth, valid, which = _nearest_plane_truth(camera, pixels, regions)
    reference = render_reference(camera, planes)
    colours, _ = reference.colours_at(pixels)
    located, located_valid, plane_id = planes.decode(colours)
    flat, _ = HomographyLocator.from_camera(camera).locate(pixels)
    on_bridge = valid & (which == 1)
    bridge = {
        "pixels_on_bridge": int(on_bridge.sum()),
        "homography_z0": _error_stats(flat, truth, on_bridge),
        "colour_16bit": _error_stats(located, truth, on_bridge & located_valid),
        "plane_id_correct_fraction": float(np.mean(plane_id[valid] == which[valid] + 1)),
    }
    # Two 50 m x 50 m areas 1 km apart: one plane over both, or one plane (B id) each.
    generator = np.random.default_rng(seed)
    points = np.concatenate(
        [
            generator.uniform(0, 50, (count // 2, 2)),
            generator.uniform(0, 50, (count // 2, 2)) + np.array([1000.0, 0.0]),
        ]
    )
    distant = {}
    for bits in (8, 16):
        big = PlaneSpec(1, (0.0, 0.0), 1050.0, 50.0, bits=bits)
        decoded, ok = big.decode(big.encode(points)[0])
        pair = PlaneSet(
            [
                PlaneSpec(1, (0.0, 0.0), 50.0, 50.0, bits=bits),
                PlaneSpec(2, (1000.0, 0.0), 50.0, 50.0, bits=bits),
            ]
        )
        colours_pair = np.concatenate(
            [pair[0].encode(points[: count // 2])[0], pair[1].encode(points[count // 2 :])[0]]
        )
        decoded_pair, ok_pair, _ = pair.decode(colours_pair)
        distant[f"{bits} bit"] = {
            "one_plane_step_m": list(big.step),
            "one_plane": _error_stats(decoded, points, ok),
            "two_planes_step_m": list(pair[0].step),
            "two_planes": _error_stats(decoded_pair, points, ok_pair),
        }
    return {"bridge": {"height_m": bridge_height, **bridge}, "distant_areas": distant}


# ---------------------------------------------------------------------- 4. camera side
def camera_side_claim(
    count: int, repeats: int, seed: int, calibration: str | Path | None
) -> dict[str, Any]:
    """What an edge camera must hold and compute per method, measured on the distorted camera."""
    bench = benchmark_camera(calibration, distorted=True)
    camera = bench.camera
    pixels = _pixels(camera, count, seed)
    reference = render_reference(camera, bench.plane(8))
    lut = LUTLocator.from_camera(camera)
    homography_only = Camera.from_homography(camera.name, camera.homography, camera.image_size)
    plain = HomographyLocator.from_camera(camera)
    rows = [
        {
            "method": "homography, exact (undistort + H^-1)",
            "camera_holds": "K, distortion, R, t (calibration)",
            "stored_bytes": len(json.dumps(camera_to_dict(camera))),
            "memory_bytes": 8 * (9 + 9 + len(camera.distortion)),
            "needs_calibration": True,
            "knows_world_coordinates": True,
            "ns_per_point": _median_ns(lambda: camera.pixel_to_world(pixels), count, repeats),
        },
        {
            "method": "homography, plain (lens ignored)",
            "camera_holds": "H (calibration)",
            "stored_bytes": len(json.dumps(camera_to_dict(homography_only))),
            "memory_bytes": 72,
            "needs_calibration": True,
            "knows_world_coordinates": True,
            "ns_per_point": _median_ns(lambda: plain.locate(pixels), count, repeats),
        },
        {
            "method": "LUT (float32 x, y per pixel)",
            "camera_holds": "H x W x 2 table",
            "stored_bytes": int(lut.table.nbytes + 128),
            "memory_bytes": int(lut.table.nbytes),
            "needs_calibration": False,
            "knows_world_coordinates": True,
            "ns_per_point": _median_ns(lambda: lut.locate(pixels), count, repeats),
        },
        {
            "method": "colour reference (ours): read, send colour",
            "camera_holds": "reference PNG (8 bit)",
            "stored_bytes": len(reference.to_png_bytes()),
            "memory_bytes": int(reference.pixels.nbytes + reference.packed.nbytes),
            "needs_calibration": False,
            "knows_world_coordinates": False,
            "ns_per_point": _median_ns(lambda: reference.colours_at(pixels), count, repeats),
        },
    ]
    return {"camera": bench.source, "rows": rows}


def benchmark_claims(
    count: int = 20_000, repeats: int = 5, seed: int = 0, calibration: str | Path | None = None
) -> dict[str, Any]:
    """All four claims; a JSON-ready dict (see the module docstring)."""
    if count <= 0 or repeats <= 0:
        raise ValueError("count and repeats must be positive")
    return json_ready(
        {
            "machine": machine_info(),
            "n": count,
            "seed": seed,
            "repeats": repeats,
            "distortion": distortion_claim(count, repeats, seed, calibration),
            "non_planar": non_planar_claim(count, seed),
            "several_planes": several_planes_claim(count, seed),
            "camera_side": camera_side_claim(count, repeats, seed, calibration),
        }
    )


def _stats_cells(stats: dict) -> list:
    return [stats["median_cm"], stats["p95_cm"], stats["max_cm"], stats["points"]]


def claims_report(result: dict[str, Any]) -> str:
    """Markdown tables of the four claims."""
    error_headers = ["median cm", "p95 cm", "max cm", "pixels"]
    distortion = result["distortion"]
    timing = distortion["timing"]
    non_planar = result["non_planar"]
    planes = result["several_planes"]
    ramp = non_planar["ramp"]
    bridge = planes["bridge"]
    lines = [
        f"### Where the reference image wins (n = {result['n']:,} random pixels, "
        f"seed {result['seed']})",
        "",
        f"#### 1. Lens distortion ({distortion['camera']})",
        "",
        markdown_table(
            ["method", *error_headers],
            [[name, *_stats_cells(stats)] for name, stats in distortion["errors"].items()],
        ),
        "",
        "Exact maths on the camera costs "
        f"{timing['undistort_then_homography_ns']:.0f} ns/point (undistort + homography) against "
        f"{timing['colour_read_ns']:.0f} ns/point for the colour read "
        f"(plain homography {timing['homography_plain_ns']:.0f} ns/point, but wrong).",
        "",
        "#### 2. Non-planar ground (built-in camera)",
        "",
        markdown_table(
            [
                "terrace height",
                "homography z=0 median cm",
                "p95 cm",
                "colour 16 bit median cm",
                "p95 cm",
            ],
            [
                [
                    name,
                    entry["homography_z0"]["median_cm"],
                    entry["homography_z0"]["p95_cm"],
                    entry["colour_16bit"]["median_cm"],
                    entry["colour_16bit"]["p95_cm"],
                ]
                for name, entry in non_planar["terraces"].items()
            ],
        ),
        "",
        f"Ramp rising {ramp['rise_m']:g} m from y = {ramp['from_y_m']:g} "
        f"to {ramp['to_y_m']:g} m, reference made of horizontal strips:",
        "",
        markdown_table(
            ["method", *error_headers],
            [[name, *_stats_cells(stats)] for name, stats in non_planar["ramp"]["errors"].items()],
        ),
        "",
        f"#### 3. Several planes: a footbridge {planes['bridge']['height_m']:g} m above the ground",
        "",
        markdown_table(
            ["method (bridge pixels)", *error_headers],
            [
                ["homography z=0", *_stats_cells(planes["bridge"]["homography_z0"])],
                ["colour, 16 bit (B = plane id)", *_stats_cells(planes["bridge"]["colour_16bit"])],
            ],
        ),
        "",
        f"Plane id (B) names the right level for {bridge['plane_id_correct_fraction']:.4f} "
        "of the pixels that see a plane.",
        "",
        "Two 50 m x 50 m areas 1 km apart, random points, encode/decode error:",
        "",
        markdown_table(
            [
                "bits",
                "one plane: step m",
                "median cm",
                "max cm",
                "two planes (B): step m",
                "median cm",
                "max cm",
            ],
            [
                [
                    bits,
                    max(entry["one_plane_step_m"]),
                    entry["one_plane"]["median_cm"],
                    entry["one_plane"]["max_cm"],
                    max(entry["two_planes_step_m"]),
                    entry["two_planes"]["median_cm"],
                    entry["two_planes"]["max_cm"],
                ]
                for bits, entry in planes["distant_areas"].items()
            ],
        ),
        "",
        f"#### 4. What the camera holds and computes ({result['camera_side']['camera']})",
        "",
        markdown_table(
            [
                "method",
                "camera holds",
                "stored bytes",
                "memory bytes",
                "needs calibration",
                "knows world coordinates",
                "batched ns/point",
            ],
            [
                [
                    row["method"],
                    row["camera_holds"],
                    row["stored_bytes"],
                    row["memory_bytes"],
                    row["needs_calibration"],
                    row["knows_world_coordinates"],
                    row["ns_per_point"],
                ]
                for row in result["camera_side"]["rows"]
            ],
        ),
        "",
        "The colour method's memory is the decoded PNG plus a packed uint64 copy kept for "
        "one-gather lookups; a camera short of memory can read the decoded pixels directly.",
    ]
    return "\n".join(lines)
