"""Figures of the lookup benchmark and of the distortion claim (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.cameras import benchmark_camera
from cblrs.bench.lookup import EXTRA_ONE_POINT, METHODS, PAPER_DEVICE
from cblrs.locate import ColorLocator, HomographyLocator
from cblrs.reference import render_reference


def _pyplot():
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib.pyplot as plt

    return plt


def plot_lookup(result: dict[str, Any], out: str | Path) -> Path:
    """ns per point, one point at a time and batched, per method, beside the paper's figures."""

    plt = _pyplot()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    labels = {"homography": "homography", "lut": "LUT", "colour": "colour (ours)"}
    paper = result["paper"]["table_i_seconds"][PAPER_DEVICE]
    positions = np.arange(len(METHODS))
    figure, axis = plt.subplots(figsize=(7.5, 4.6))
    width = 0.27
    one = [result["one_point"][method]["ns_per_point"] for method in METHODS]
    batched = [result["batched"][method]["ns_per_point"] for method in METHODS]
    paper_ns = [paper[method] / result["paper"]["n"] * 1e9 for method in METHODS]
    axis.bar(
        positions - width, paper_ns, width, label=f"paper, one point ({PAPER_DEVICE})", color="0.7"
    )
    axis.bar(positions, one, width, label="this machine, one point (Python loop)", color="C0")
    axis.bar(positions + width, batched, width, label="this machine, batched (numpy)", color="C2")
    numpy_one = result["one_point"][EXTRA_ONE_POINT]["ns_per_point"]
    axis.axhline(
        numpy_one,
        color="C3",
        linestyle="--",
        linewidth=1,
        label="homography with a numpy 3x3 product per point",
    )
    axis.axhline(
        result["batched"]["colour_read_only"]["ns_per_point"],
        color="C1",
        linestyle=":",
        linewidth=1,
        label="colour read only, batched (camera side)",
    )
    axis.set_xticks(positions, [labels[method] for method in METHODS])
    axis.set_yscale("log")
    axis.set_ylabel("nanoseconds per point")
    axis.set_title(f"Pixel -> world lookup, n = {result['n']:,} random pixels of a 1080p camera")
    axis.grid(alpha=0.3, axis="y", which="both")
    figure.legend(fontsize=7, loc="lower center", ncol=2, frameon=False)
    figure.tight_layout(rect=(0, 0.16, 1, 1))
    path = out / "lookup_table_i.png"
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return path


def plot_distortion_error(
    calibration: str | Path | None, out: str | Path, step_px: int = 8
) -> Path:
    """Per-pixel error (cm) of a plain homography and of the 16-bit colour lookup on the
    distorted benchmark camera, against the exact ray-plane intersection."""

    plt = _pyplot()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bench = benchmark_camera(calibration, distorted=True)
    camera = bench.camera
    width, height = camera.image_size
    columns, rows = np.meshgrid(np.arange(0, width, step_px), np.arange(0, height, step_px))
    pixels = np.column_stack([columns.ravel(), rows.ravel()]).astype(np.float64)
    truth, valid = camera.pixel_to_world(pixels)
    x0, y0, plane_width, plane_length = bench.ground
    with np.errstate(invalid="ignore"):
        valid &= (truth[:, 0] >= x0) & (truth[:, 0] <= x0 + plane_width)
        valid &= (truth[:, 1] >= y0) & (truth[:, 1] <= y0 + plane_length)
    plain, _ = HomographyLocator.from_camera(camera).locate(pixels)
    colour, colour_valid = ColorLocator(render_reference(camera, bench.plane(16))).locate(pixels)
    maps = []
    for estimate, ok in ((plain, valid), (colour, valid & colour_valid)):
        error = np.where(ok, np.hypot(*(estimate - truth).T) * 100.0, np.nan)
        maps.append(error.reshape(rows.shape))
    figure, axes = plt.subplots(1, 2, figsize=(10, 3.2), constrained_layout=True)
    titles = ["plain homography (lens ignored)", "colour reference, 16 bit"]
    for axis, error, title in zip(axes, maps, titles, strict=True):
        image = axis.imshow(
            error,
            extent=(0, width, height, 0),
            cmap="magma",
            vmin=0,
            vmax=max(float(np.nanpercentile(maps[0], 95)), 1.0),
        )
        axis.set_title(f"{title}: median {np.nanmedian(error):.2g} cm", fontsize=9)
        axis.set_xticks([])
        axis.set_yticks([])
    figure.colorbar(image, ax=axes, label="ground error (cm)", shrink=0.9)
    figure.suptitle(
        f"Lookup error on the distorted camera ({camera.name}), pixels on the plane", fontsize=10
    )
    path = out / "claims_distortion.png"
    figure.savefig(path, dpi=80)
    plt.close(figure)
    return path
