"""The paper's section IV-B on the synthetic world: where in a box should a camera look?

Setup (all exact geometry, see :mod:`cblrs.datasets.synthetic`): a 1920x1080 camera 8 m above
the ground, looking along world +x and tilted down by 10..90 degrees. Objects (car 4.5 x 1.8 x
1.5 m, person 0.5 x 0.5 x 1.75 m) stand at a grid of positions in the lower image, headed at
yaw 0, 45 or 90 degrees relative to the viewing direction (0 = seen from behind, 90 =
broadside). Only positions whose box lies wholly in the image are used.

For a fixed targeting position (horizontal centre, vertical VTP from the top), the target
pixel's ground point (through the camera's ground homography, i.e. what a colour lookup
returns) is compared with the true footprint centre: the average offset distance (AOD, m).
The signed offset along the line of sight tells whether the target lands between camera and
object (negative) or behind it (positive).

Two conditions: "exact" boxes (the projected 3D boxes, as the paper's hand labels) and
"noisy" boxes (object sizes drawn +-10 % around the class prior, box edges jittered by 2 % of
the box height; several draws per position), under which the geometric targeter of
:mod:`cblrs.geometric_targeting` (which only knows the class prior) is compared with the best
fixed VTP chosen with hindsight for each tilt.

The experiment, its markdown table and its figure read and write the same result dictionary, so
they stay together here; the same comparison on data-set scenes (WILDTRACK's annotated boxes,
the tracking metrics) is in :mod:`cblrs.experiments.targeting_scenes`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.bench.machine import json_ready
from cblrs.bench.report import markdown_table
from cblrs.camera import Camera
from cblrs.datasets.synthetic import project_boxes_3d
from cblrs.geometric_targeting import DEFAULT_CLASS_SIZES, GeometricTargeter
from cblrs.targeting import target_pixels

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

CONDITIONS = ("exact", "noisy")


@dataclass(frozen=True)
class TargetingSetup:
    """Parameters of the targeting experiment (defaults reproduce the documented run)."""

    classes: tuple[str, ...] = ("car", "person")
    tilts_deg: tuple[float, ...] = (10, 20, 30, 40, 50, 60, 70, 80, 90)
    yaws_deg: tuple[float, ...] = (0, 45, 90)
    vtps: tuple[float, ...] = (*(round(0.5 + 0.05 * step, 2) for step in range(10)), 1.0)
    camera_height_m: float = 8.0
    focal_px: float = 1200.0
    image_size: tuple[int, int] = (1920, 1080)
    grid_x: tuple[float, ...] = (0.3, 0.5, 0.7)
    grid_y: tuple[float, ...] = (0.5, 0.65, 0.8)
    size_jitter: float = 0.10
    edge_noise: float = 0.02
    noise_draws: int = 4
    seed: int = 0
    class_sizes: dict[str, tuple[float, float, float]] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_SIZES)
    )


def experiment_camera(setup: TargetingSetup, tilt_deg: float) -> Camera:
    """The experiment's camera at a tilt (degrees below the horizon)."""
    return Camera.from_pose(
        f"tilt{tilt_deg:g}",
        position=(0.0, 0.0, setup.camera_height_m),
        pan_deg=0.0,
        tilt_deg=float(tilt_deg),
        focal_px=setup.focal_px,
        image_size=setup.image_size,
    )


def object_positions(
    camera: Camera, setup: TargetingSetup, size_lwh: NDArray, yaw_deg: float
) -> tuple[FloatArray, FloatArray]:
    """Footprint centres on the image grid whose boxes lie wholly inside the image.

    Returns:
        ``(centres, xyxy)``: (P, 2) metres and (P, 4) pixels of the exact boxes.
    """
    width, height = camera.image_size
    grid = np.array(
        [(fx * (width - 1), fy * (height - 1)) for fy in setup.grid_y for fx in setup.grid_x]
    )
    centres, valid = camera.pixel_to_world(grid)
    centres = centres[valid]
    xyxy, visible = project_boxes_3d(camera, centres, size_lwh, yaw_deg)
    with np.errstate(invalid="ignore"):
        whole = (
            visible
            & (xyxy[:, 0] > 0.5)
            & (xyxy[:, 1] > 0.5)
            & (xyxy[:, 2] < width - 1.5)
            & (xyxy[:, 3] < height - 1.5)
        )
    return centres[whole], xyxy[whole]


def _noisy_boxes(
    camera: Camera,
    centres: FloatArray,
    size_lwh: NDArray,
    yaw_deg: float,
    setup: TargetingSetup,
    generator: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Boxes of objects of jittered size with jittered edges; (centres, xyxy) kept in view."""
    draws = setup.noise_draws
    repeated = np.repeat(centres, draws, axis=0)
    sizes = np.asarray(size_lwh) * generator.uniform(
        1 - setup.size_jitter, 1 + setup.size_jitter, (len(repeated), 3)
    )
    xyxy, visible = project_boxes_3d(camera, repeated, sizes, yaw_deg)
    box_height = (xyxy[:, 3] - xyxy[:, 1])[:, None]
    xyxy = xyxy + generator.normal(0.0, 1.0, xyxy.shape) * setup.edge_noise * box_height
    xyxy[:, [0, 2]] = np.sort(xyxy[:, [0, 2]], axis=1)
    xyxy[:, [1, 3]] = np.sort(xyxy[:, [1, 3]], axis=1)
    return repeated[visible], xyxy[visible]


def offsets(
    camera: Camera, target_pixels_xy: FloatArray, centres: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Distance (m) from each target's ground point to the true centre, and its signed part
    along the line of sight (negative: between camera and object)."""
    ground, valid = camera.pixel_to_world(target_pixels_xy)
    difference = ground - centres
    distance = np.where(valid, np.hypot(difference[:, 0], difference[:, 1]), np.inf)
    sight = centres - camera.centre[:2]
    norm = np.linalg.norm(sight, axis=1, keepdims=True)
    # Straight below the camera there is no line of sight on the ground; use the view axis.
    forward = camera.rotation[2, :2] if camera.rotation is not None else np.array([1.0, 0.0])
    forward = forward / max(float(np.linalg.norm(forward)), 1e-12)
    direction = np.where(norm > 1e-6, sight / np.maximum(norm, 1e-12), forward)
    along = np.where(valid, np.sum(difference * direction, axis=1), np.nan)
    return distance, along


def run_targeting(setup: TargetingSetup | None = None) -> dict[str, Any]:
    """Run the experiment.

    Returns:
        A JSON-ready dict. ``aod[condition][class][yaw][tilt]`` lists the AOD (m) per VTP
        (``vtps``); ``along_bottom[class][tilt]`` is the mean signed offset (m) of the
        bottom-centre target; ``geometric[condition][class][tilt]`` the geometric targeter's
        AOD; ``summary[condition][class]`` per tilt: best VTP, its AOD, the geometric AOD
        and their ratio.
    """
    setup = setup or TargetingSetup()
    generator = np.random.default_rng(setup.seed)
    vtps = list(setup.vtps)
    aod: dict[str, dict] = {condition: {} for condition in CONDITIONS}
    geometric: dict[str, dict] = {condition: {} for condition in CONDITIONS}
    along_bottom: dict[str, dict] = {}
    along_by_vtp: dict[str, dict] = {}
    positions: dict[str, dict] = {}
    for class_name in setup.classes:
        size = np.asarray(setup.class_sizes[class_name], dtype=np.float64)
        for condition in CONDITIONS:
            aod[condition][class_name] = {str(yaw): {} for yaw in setup.yaws_deg}
            geometric[condition][class_name] = {}
        along_bottom[class_name] = {}
        along_by_vtp[class_name] = {}
        positions[class_name] = {}
        for tilt in setup.tilts_deg:
            camera = experiment_camera(setup, tilt)
            targeter = GeometricTargeter(camera, {class_name: tuple(size)})
            geometric_distances: dict[str, list] = {condition: [] for condition in CONDITIONS}
            along_sums = np.zeros(len(vtps))
            along_count = 0
            counts = []
            for yaw in setup.yaws_deg:
                centres, exact = object_positions(camera, setup, size, yaw)
                counts.append(len(centres))
                if len(centres) == 0:
                    for condition in CONDITIONS:
                        aod[condition][class_name][str(yaw)][str(tilt)] = [None] * len(vtps)
                    continue
                noisy_centres, noisy = _noisy_boxes(camera, centres, size, yaw, setup, generator)
                cases = {"exact": (centres, exact), "noisy": (noisy_centres, noisy)}
                for condition, (truth, boxes) in cases.items():
                    row = []
                    for index, vtp in enumerate(vtps):
                        pixels, _ = target_pixels(boxes, 0.5, vtp)
                        distance, along = offsets(camera, pixels, truth)
                        row.append(float(np.mean(distance)))
                        if condition == "exact":
                            along_sums[index] += float(np.sum(along))
                    if condition == "exact":
                        along_count += len(truth)
                    aod[condition][class_name][str(yaw)][str(tilt)] = row
                    pixels, _ = targeter.pixels_for(boxes, size)
                    distance, _ = offsets(camera, np.nan_to_num(pixels, nan=-1e6), truth)
                    geometric_distances[condition].append(distance)
            positions[class_name][str(tilt)] = counts
            along_by_vtp[class_name][str(tilt)] = (
                (along_sums / along_count).tolist() if along_count else [None] * len(vtps)
            )
            along_bottom[class_name][str(tilt)] = along_by_vtp[class_name][str(tilt)][-1]
            for condition in CONDITIONS:
                values = geometric_distances[condition]
                geometric[condition][class_name][str(tilt)] = (
                    float(np.mean(np.concatenate(values))) if values else None
                )
    summary = _summarise(setup, vtps, aod, geometric)
    return _json_ready(
        {
            "setup": {
                "classes": list(setup.classes),
                "class_sizes_lwh_m": {
                    name: list(setup.class_sizes[name]) for name in setup.classes
                },
                "tilts_deg": list(setup.tilts_deg),
                "yaws_deg": list(setup.yaws_deg),
                "vtps": vtps,
                "camera_height_m": setup.camera_height_m,
                "focal_px": setup.focal_px,
                "image_size": list(setup.image_size),
                "grid": {"x": list(setup.grid_x), "y": list(setup.grid_y)},
                "size_jitter": setup.size_jitter,
                "edge_noise": setup.edge_noise,
                "noise_draws": setup.noise_draws,
                "seed": setup.seed,
            },
            "positions": positions,
            "aod": aod,
            "along": along_by_vtp,
            "along_bottom": along_bottom,
            "geometric": geometric,
            "summary": summary,
        }
    )


def _summarise(
    setup: TargetingSetup, vtps: list[float], aod: dict, geometric: dict
) -> dict[str, Any]:
    """Best fixed VTP per tilt (mean over yaws) against the geometric targeter."""
    paper_range = [index for index, vtp in enumerate(vtps) if vtp <= 0.95 + 1e-9]
    summary: dict[str, Any] = {}
    for condition in CONDITIONS:
        summary[condition] = {}
        for class_name in setup.classes:
            rows = []
            for tilt in setup.tilts_deg:
                table = np.array(
                    [
                        [
                            np.nan if value is None else value
                            for value in aod[condition][class_name][str(yaw)][str(tilt)]
                        ]
                        for yaw in setup.yaws_deg
                    ],
                    dtype=np.float64,
                )
                if np.all(np.isnan(table)):
                    continue
                mean_over_yaws = np.nanmean(table, axis=0)
                best = min(paper_range, key=lambda index: mean_over_yaws[index])
                best_any = int(np.nanargmin(mean_over_yaws))
                geometric_aod = geometric[condition][class_name][str(tilt)]
                rows.append(
                    {
                        "tilt_deg": tilt,
                        "best_vtp": vtps[best_any],
                        "best_vtp_aod_m": float(mean_over_yaws[best_any]),
                        "best_vtp_50_95": vtps[best],
                        "best_vtp_50_95_aod_m": float(mean_over_yaws[best]),
                        "bottom_centre_aod_m": float(mean_over_yaws[-1]),
                        "vtp50_aod_m": float(mean_over_yaws[0]),
                        "geometric_aod_m": geometric_aod,
                        "geometric_over_best": (
                            geometric_aod / float(mean_over_yaws[best_any])
                            if geometric_aod is not None
                            else None
                        ),
                    }
                )
            ratios = [
                row["geometric_over_best"] for row in rows if row["geometric_over_best"] is not None
            ]
            summary[condition][class_name] = {
                "per_tilt": rows,
                "fixed_mean_aod_m": float(
                    np.nanmean(
                        [
                            np.nan if value is None else value
                            for yaw in setup.yaws_deg
                            for tilt in setup.tilts_deg
                            for value in aod[condition][class_name][str(yaw)][str(tilt)][
                                : len(paper_range)
                            ]
                        ]
                    )
                ),
                "worst_ratio": max(ratios) if ratios else None,
                "meets_30_percent": bool(ratios) and max(ratios) <= 0.7,
            }
    return summary


def _json_ready(value: Any) -> Any:
    return json_ready(value)


def targeting_report(result: dict[str, Any]) -> str:
    """Markdown: AOD per tilt x VTP (mean over yaws), best VTP per tilt, geometric targeting."""

    setup = result["setup"]
    vtps = setup["vtps"]
    lines = [
        "### Targeting (section IV-B) on the synthetic world",
        "",
        f"Camera {setup['camera_height_m']:g} m high, f = {setup['focal_px']:g} px, "
        f"{setup['image_size'][0]}x{setup['image_size'][1]}; yaws {setup['yaws_deg']} deg; "
        "AOD in metres, mean over yaws and positions. VTP 1.0 = bottom centre.",
    ]
    for class_name in setup["classes"]:
        size = setup["class_sizes_lwh_m"][class_name]
        lines += [
            "",
            f"#### {class_name} ({size[0]:g} x {size[1]:g} x {size[2]:g} m), exact boxes",
            "",
        ]
        headers = ["tilt"] + [f"{vtp:.2f}" for vtp in vtps]
        rows = []
        for tilt in setup["tilts_deg"]:
            table = np.array(
                [
                    [
                        np.nan if value is None else value
                        for value in result["aod"]["exact"][class_name][str(yaw)][str(tilt)]
                    ]
                    for yaw in setup["yaws_deg"]
                ],
                dtype=np.float64,
            )
            rows.append([f"{tilt:g}"] + [float(value) for value in np.nanmean(table, axis=0)])
        lines.append(markdown_table(headers, rows))
        for condition in CONDITIONS:
            summary = result["summary"][condition][class_name]
            lines += [
                "",
                f"{class_name}, {condition} boxes: best fixed VTP per tilt vs geometric targeting",
                "",
                markdown_table(
                    [
                        "tilt",
                        "best fixed VTP",
                        "its AOD m",
                        "bottom centre AOD m",
                        "geometric AOD m",
                        "geometric / best fixed",
                    ],
                    [
                        [
                            f"{row['tilt_deg']:g}",
                            f"{row['best_vtp']:.2f}",
                            row["best_vtp_aod_m"],
                            row["bottom_centre_aod_m"],
                            row["geometric_aod_m"],
                            row["geometric_over_best"],
                        ]
                        for row in summary["per_tilt"]
                    ],
                ),
                "",
                f"Mean AOD of fixed VTPs 50-95 %: {summary['fixed_mean_aod_m']:.3f} m; worst "
                f"geometric / best-fixed ratio {summary['worst_ratio']:.3f} "
                f"({'meets' if summary['meets_30_percent'] else 'misses'} the 30 % target).",
            ]
        along = result["along_bottom"][class_name]
        lines += [
            "",
            "Bottom-centre target, mean signed offset along the line of sight (negative = "
            "between camera and object): "
            + ", ".join(
                f"{tilt}deg {value:+.2f} m" for tilt, value in along.items() if value is not None
            ),
        ]
    tracking = result.get("tracking")
    if tracking:
        lines += [
            "",
            "#### Effect on tracking (default pipeline, box vs geometric targeting)",
            "",
            markdown_table(
                ["scene", "targeting", "HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1", "seconds"],
                [
                    [
                        scene,
                        mode,
                        values["HOTA"],
                        values["DetA"],
                        values["AssA"],
                        values["LocA"],
                        values["MOTA"],
                        values["IDF1"],
                        values["seconds"],
                    ]
                    for scene, modes in tracking.items()
                    for mode, values in modes.items()
                ],
            ),
        ]
    wildtrack = result.get("wildtrack")
    if wildtrack:
        lines += [
            "",
            "#### WILDTRACK annotated boxes (people): target ground point vs annotated position",
            "",
            markdown_table(
                ["camera", "boxes", "bottom centre median m", "geometric median m"],
                [
                    [
                        name,
                        entry["boxes"],
                        entry["bottom_centre"]["median_m"],
                        entry["geometric"]["median_m"],
                    ]
                    for name, entry in wildtrack["cameras"].items()
                ]
                + [
                    [
                        "all",
                        sum(entry["boxes"] for entry in wildtrack["cameras"].values()),
                        wildtrack["overall"]["bottom_centre"]["median_m"],
                        wildtrack["overall"]["geometric"]["median_m"],
                    ]
                ],
            ),
        ]
    return "\n".join(lines)


def plot_targeting(result: dict[str, Any], out: str | Path) -> list[Path]:
    """Heat maps (tilt x VTP, one panel per yaw) per class, and geometric vs best fixed VTP.

    Returns:
        The PNG paths written.
    """
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    setup = result["setup"]
    vtps = setup["vtps"]
    tilts = setup["tilts_deg"]
    written = []
    for class_name in setup["classes"]:
        figure, axes = plt.subplots(
            1,
            len(setup["yaws_deg"]),
            figsize=(3.6 * len(setup["yaws_deg"]) + 1.0, 3.6),
            sharey=True,
            constrained_layout=True,
        )
        axes = np.atleast_1d(axes)
        tables = [
            np.array(
                [
                    [
                        np.nan if value is None else value
                        for value in result["aod"]["exact"][class_name][str(yaw)][str(tilt)]
                    ]
                    for tilt in tilts
                ],
                dtype=np.float64,
            )
            for yaw in setup["yaws_deg"]
        ]
        top = float(np.nanpercentile(np.concatenate([table.ravel() for table in tables]), 95))
        for axis, yaw, table in zip(axes, setup["yaws_deg"], tables, strict=True):
            image = axis.imshow(
                table, aspect="auto", origin="lower", cmap="viridis", vmin=0, vmax=top
            )
            axis.set_xticks(range(len(vtps)), [f"{vtp * 100:.0f}" for vtp in vtps], fontsize=7)
            axis.set_yticks(range(len(tilts)), [f"{tilt:g}" for tilt in tilts])
            axis.set_xlabel("VTP (% of box height from top)")
            axis.set_title(f"{class_name}, yaw {yaw:g} deg")
            best = np.nanargmin(table[:, :-1], axis=1)
            axis.plot(best, range(len(tilts)), "w.", markersize=6)
        axes[0].set_ylabel("camera tilt (deg)")
        figure.colorbar(image, ax=axes, label="AOD (m)", shrink=0.9)
        figure.suptitle(f"{class_name}: average offset distance; dots = best VTP per tilt")
        path = out / f"targeting_{class_name}.png"
        figure.savefig(path, dpi=90)
        plt.close(figure)
        written.append(path)

    figure, axes = plt.subplots(
        1, len(setup["classes"]), figsize=(5.2 * len(setup["classes"]), 3.6)
    )
    axes = np.atleast_1d(axes)
    for axis, class_name in zip(axes, setup["classes"], strict=True):
        for condition, style in (("exact", "-"), ("noisy", "--")):
            rows = result["summary"][condition][class_name]["per_tilt"]
            x = [row["tilt_deg"] for row in rows]
            axis.plot(
                x,
                [row["best_vtp_aod_m"] for row in rows],
                "C0" + style,
                marker="o",
                label=f"best fixed VTP ({condition})",
            )
            axis.plot(
                x,
                [row["bottom_centre_aod_m"] for row in rows],
                "C1" + style,
                marker="s",
                label=f"bottom centre ({condition})",
            )
            axis.plot(
                x,
                [row["geometric_aod_m"] for row in rows],
                "C2" + style,
                marker="^",
                label=f"geometric ({condition})",
            )
        axis.set_xlabel("camera tilt (deg)")
        axis.set_ylabel("AOD (m)")
        axis.set_title(class_name)
        axis.set_ylim(bottom=0)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    path = out / "targeting_geometric.png"
    figure.savefig(path, dpi=90)
    plt.close(figure)
    written.append(path)
    return written
