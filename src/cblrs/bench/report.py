"""Markdown tables of benchmark and experiment results (the CLI prints them, docs/ keeps them)."""

from __future__ import annotations

import math
from typing import Any

from cblrs.bench.lookup import EXTRA_ONE_POINT, METHODS, PAPER_DEVICE
from cblrs.bench.machine import describe_machine


def markdown_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A GitHub-flavoured markdown table; floats keep 4 significant figures."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(_cell(value) for value in row) + " |")
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "-"
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:,.0f}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def _bytes(count: float) -> str:
    for unit, size in (("MiB", 2**20), ("KiB", 2**10)):
        if count >= size:
            return f"{count / size:.1f} {unit}"
    return f"{count:.0f} B"


def lookup_report(result: dict[str, Any]) -> str:
    """Table I next to the paper's i5-4690K figures, batched figures, sizes."""

    paper = result["paper"]["table_i_seconds"][PAPER_DEVICE]
    count = result["n"]
    scale = result["paper"]["n"] / count
    labels = {
        "homography": "Homography",
        "lut": "Lookup table",
        "colour": "Colour (ours)",
        EXTRA_ONE_POINT: "Homography, numpy 3x3 product per point",
    }
    rows = []
    for method in (*METHODS, EXTRA_ONE_POINT):
        one = result["one_point"][method]
        batched = result["batched"].get(method)
        rows.append(
            [
                labels[method],
                one["median"],
                f"{one['min']:.4g}..{one['max']:.4g}",
                one["ns_per_point"],
                paper.get(method, float("nan")) / scale,
                batched["ns_per_point"] if batched else float("nan"),
            ]
        )
    read = result["batched"]["colour_read_only"]
    rows.append(
        [
            "Colour read only (camera side)",
            float("nan"),
            "",
            float("nan"),
            float("nan"),
            read["ns_per_point"],
        ]
    )
    ratios = result["ratios"]
    sizes = result["sizes_bytes"]
    paper_sizes = result["paper"]["sizes_bytes"]
    camera = result["camera"]
    agreement = result["agreement"]
    text = [
        f"### Table I on this machine (n = {count:,}, seed {result['seed']}, "
        f"median of {result['one_point']['colour']['repeats']} runs)",
        "",
        describe_machine(result["machine"]),
        f"camera: {camera['source']}, {camera['image_size'][0]}x{camera['image_size'][1]}, "
        f"ground {camera['ground']} m, {camera['bits']}-bit reference",
        "",
        markdown_table(
            [
                "method",
                "one point: s (median)",
                "min..max s",
                "ns/point",
                f"paper {PAPER_DEVICE}, s",
                "batched ns/point",
            ],
            rows,
        ),
        "",
        markdown_table(
            ["ratio", "this machine, one point", "this machine, batched", "paper"],
            [
                [
                    "colour / homography",
                    ratios["one_point_colour_over_homography"],
                    ratios["batched_colour_over_homography"],
                    ratios["paper_colour_over_homography"],
                ],
                [
                    "LUT / homography",
                    ratios["one_point_lut_over_homography"],
                    ratios["batched_lut_over_homography"],
                    ratios["paper_lut_over_homography"],
                ],
                [
                    "colour / LUT",
                    ratios["one_point_colour_over_lut"],
                    result["batched"]["colour"]["median"] / result["batched"]["lut"]["median"],
                    ratios["paper_colour_over_lut"],
                ],
                [
                    "colour / homography (numpy per point)",
                    ratios["one_point_colour_over_homography_numpy"],
                    float("nan"),
                    float("nan"),
                ],
            ],
        ),
        "",
        markdown_table(
            ["stored file", "bytes", "size", "paper"],
            [
                [
                    "LUT (.npy, float32 H x W x 2)",
                    sizes["lut_npy_float32"],
                    _bytes(sizes["lut_npy_float32"]),
                    _bytes(paper_sizes["lut"]),
                ],
                [
                    "reference PNG, 8 bit",
                    sizes["png_8bit"],
                    _bytes(sizes["png_8bit"]),
                    _bytes(paper_sizes["png"]),
                ],
                ["reference PNG, 16 bit", sizes["png_16bit"], _bytes(sizes["png_16bit"]), "-"],
                [
                    "homography JSON",
                    sizes["homography_json"],
                    _bytes(sizes["homography_json"]),
                    _bytes(paper_sizes["homography_json"]),
                ],
                [
                    "full calibration JSON (K, distortion, R, t)",
                    sizes["full_calibration_json"],
                    _bytes(sizes["full_calibration_json"]),
                    "-",
                ],
            ],
        ),
        "",
        "Agreement: valid fractions "
        + ", ".join(f"{k} {v:.3f}" for k, v in result["agreement"]["valid_fraction"].items())
        + f"; colour vs homography at most {agreement['colour_vs_homography_max_m']:.4f} m"
        f" (half a cell diagonal: {agreement['half_cell_diagonal_m']:.4f} m).",
        "Measured while other jobs shared the CPU; compare ratios rather than absolute times.",
    ]
    return "\n".join(text)


def render_report(result: dict[str, Any]) -> str:
    """Render/save/load times per bit depth and lens model."""
    rows = []
    for row in result["rows"]:
        rows.append(
            [
                row["bits"],
                "distorted" if row["distorted"] else "undistorted",
                row["cold_ms"],
                row["warm_ms"]["median"],
                f"{row['warm_ms']['min']:.1f}..{row['warm_ms']['max']:.1f}",
                row["save_ms"]["median"],
                row["load_ms"]["median"],
                row["lut_build_ms"]["median"],
                _bytes(row["png_bytes"]),
                row["meets_target"],
            ]
        )
    return "\n".join(
        [
            f"### Reference rendering, 1920x1080 (median of {result['repeats']} warm runs)",
            "",
            describe_machine(result["machine"]),
            f"camera: {result['camera']['source']}",
            "",
            markdown_table(
                [
                    "bits",
                    "lens",
                    "cold ms",
                    "warm ms (median)",
                    "warm min..max",
                    "save PNG ms",
                    "load PNG ms",
                    "build LUT ms",
                    "PNG size",
                    f"< {result['target_ms']:.0f} ms",
                ],
                rows,
            ),
        ]
    )
