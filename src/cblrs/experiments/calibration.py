"""How good is a clicked calibration? (issue 11, item 4)

On WILDTRACK, for each camera, ``N`` correspondences are taken the way a person would click
them: box bottom centres of people in a few frames, paired with those people's annotated
ground positions, spread over the image (farthest-point sampling from a seeded start, so
neither the best-fitting points nor a cluster), each pixel moved by seeded Gaussian noise
(2 px by default) to mimic clicking. The points go into a site file as ``points:`` (the path a
user takes, stating the default noise of ``cblrs calibrate``: 2 px clicks, 0.1 m on the
ground), which
calibrates every camera on load (:func:`cblrs.calibrate.calibrate_camera`, model ``auto``: of
the models the points allow (a homography from 4 points, pose + focal length from 6, + k1
from 8) the one that best predicts held-out points); then every camera's reference is
rendered from it, all 200 frames are tracked with the default pipeline (fusion, the cameras'
positions from the fits) and scored.

The clicks carry WILDTRACK's own annotation offsets too: a box bottom is not exactly where the
annotated ground position projects (3-14 px median per camera under the lab calibration, up
to 45 px for people near a camera, a few centimetres on the ground there). The user does not
know these; the stated noise is the same for every run.

Reported per ``N`` (over the seeds): the localisation error of every annotated box (its
target pixel's colour decoded to metres, against its annotated position; median and p95,
metres, all cameras and frames), the tracking scores, and their difference to the lab
calibration run the same way.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cblrs.bench.machine import json_ready
from cblrs.calibrate import Correspondences, calibrate_camera
from cblrs.datasets.scene import Scene
from cblrs.errors import CalibrationError
from cblrs.evaluation import evaluate
from cblrs.pipeline import camera_positions, render_scene_references, scene_messages, track_scene
from cblrs.site.core import site_from_document
from cblrs.viz.calibration import calibration_picture
from cblrs.viz.overlay import save_image

logger = logging.getLogger(__name__)

# Sets of points a user would click before giving up on a camera.
_ATTEMPTS = 10
SCORES = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")


@dataclass(frozen=True)
class CalibrationSetup:
    """Parameters of the experiment.

    Attributes:
        counts: correspondences per camera to try.
        seeds: one run per seed (which points are picked first, and the click noise).
        noise_px: standard deviation of the click noise, pixels (per coordinate).
        point_frames: how many frames, spread over the sequence, the points come from.
        click_px: the click noise the site file states, pixels (``cblrs calibrate``'s default).
        ground_m: the ground accuracy the site file states, metres (its default).
    """

    counts: tuple[int, ...] = (4, 6, 10, 20)
    seeds: tuple[int, ...] = (0, 1, 2)
    noise_px: float = 2.0
    point_frames: int = 5
    click_px: float = 2.0
    ground_m: float = 0.1


def candidate_points(scene: Scene, camera_index: int, frame_indices: list[int]) -> dict[str, Any]:
    """Clickable points of one camera: bottom centres of whole boxes in the given frames.

    Returns:
        ``{"image_xy": (M, 2), "world_xy": (M, 2), "names": [...]}``: the box bottom centre
        (pixels), the person's annotated ground position (metres) and ``"f<frame>-p<id>"``.
    """
    camera = scene.cameras[camera_index]
    width, height = camera.image_size
    truth = scene.ground_truth
    image, world, names = [], [], []
    for index in frame_indices:
        frame = int(scene.frames[index])
        detections = scene.detections[index][camera_index]
        rows = truth.frame == frame
        positions = dict(zip(truth.track_id[rows].tolist(), truth.world_xy[rows], strict=True))
        for box, person in zip(detections.xyxy, detections.object_id.tolist(), strict=True):
            x0, y0, x1, y1 = box
            # Only whole boxes: a person cut by the image border has no visible feet.
            if x0 < 0 or y0 < 0 or x1 > width - 1 or y1 > height - 1 or person not in positions:
                continue
            image.append([(x0 + x1) / 2.0, y1])
            world.append(positions[person])
            names.append(f"f{frame}-p{person}")
    return {
        "image_xy": np.array(image, dtype=np.float64).reshape(-1, 2),
        "world_xy": np.array(world, dtype=np.float64).reshape(-1, 2),
        "names": names,
    }


def spread_choice(image_xy: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``count`` points spread over the image: a random first one, then each time
    the point farthest from those chosen (as someone clicking "one here, one there" would)."""
    if len(image_xy) < count:
        raise ValueError(f"only {len(image_xy)} candidate points for {count}")
    chosen = [int(rng.integers(len(image_xy)))]
    distance = np.hypot(*(image_xy - image_xy[chosen[0]]).T)
    while len(chosen) < count:
        index = int(np.argmax(distance))
        chosen.append(index)
        distance = np.minimum(distance, np.hypot(*(image_xy - image_xy[index]).T))
    return np.array(chosen)


def clicked_site(scene: Scene, count: int, seed: int, setup: CalibrationSetup) -> dict[str, Any]:
    """A site document whose cameras are given by ``count`` clicked points each."""
    rng = np.random.default_rng(seed)
    frame_indices = np.linspace(0, len(scene.frames) - 1, setup.point_frames).round()
    frame_list = sorted({int(index) for index in frame_indices})
    plane = scene.plane
    cameras = []
    refused = {}
    for camera_index, camera in enumerate(scene.cameras):
        candidates = candidate_points(scene, camera_index, frame_list)
        # A set of points that cannot calibrate (e.g. 4 points with 3 nearly on one line) is
        # refused by `calibrate_camera`, as it would be for a user, who would then click
        # another set: so does the experiment (counted as `refused`).
        for attempt in range(_ATTEMPTS):
            chosen = spread_choice(candidates["image_xy"], count, rng)
            clicks = candidates["image_xy"][chosen] + rng.normal(0.0, setup.noise_px, (count, 2))
            points = [
                [float(u), float(v), float(x), float(y), candidates["names"][index]]
                for (u, v), (x, y), index in zip(
                    clicks, candidates["world_xy"][chosen], chosen.tolist(), strict=True
                )
            ]
            try:
                calibrate_camera(
                    Correspondences.from_rows(points),
                    camera.image_size,
                    camera.name,
                    click_px=setup.click_px,
                    ground_m=setup.ground_m,
                )
                break
            except CalibrationError:
                if attempt == _ATTEMPTS - 1:
                    raise
        refused[camera.name] = attempt
        cameras.append(
            {
                "name": camera.name,
                "image_size": list(camera.image_size),
                "points": points,
                "click_px": setup.click_px,
                "ground_m": setup.ground_m,
            }
        )
    return {
        "refused": refused,
        "version": 1,
        "name": f"{scene.name} clicked {count}",
        "planes": [
            {
                "id": plane.plane_id,
                "origin": list(plane.origin),
                "size": [plane.width, plane.length],
                "bits": plane.bits,
            }
        ],
        "cameras": cameras,
    }


def localisation_errors(scene: Scene, references: list) -> np.ndarray:
    """Distance (metres) between each annotated box's located target and its annotated
    position, over all frames and cameras; boxes whose target sees no plane are left out."""

    truth = scene.ground_truth
    positions = {
        (int(frame), int(person)): xy
        for frame, person, xy in zip(truth.frame, truth.track_id, truth.world_xy, strict=True)
    }
    planes = references[0].planes
    errors = []
    for index, (_, messages) in enumerate(scene_messages(scene, references)):
        frame = int(scene.frames[index])
        for camera_index, message in enumerate(messages):
            located, valid, _ = planes.decode(message.colour)
            people = scene.detections[index][camera_index].object_id
            for xy, ok, person in zip(located, valid, people.tolist(), strict=True):
                key = (frame, int(person))
                if ok and key in positions:
                    errors.append(float(np.hypot(*(xy - positions[key]))))
    return np.array(errors)


# Bins of predicted ground error (metres) in which the real error is compared.
PREDICTED_BINS = (0.0, 0.1, 0.2, 0.5, float("inf"))


def box_pixels(scene: Scene, camera_index: int) -> tuple[np.ndarray, np.ndarray]:
    """Bottom centres (pixels) of every annotated box of a camera, and the annotated ground
    positions (metres) of those people: ``((M, 2), (M, 2))``."""
    truth = scene.ground_truth
    positions = {
        (int(frame), int(person)): xy
        for frame, person, xy in zip(truth.frame, truth.track_id, truth.world_xy, strict=True)
    }
    pixels, world = [], []
    for index, frame in enumerate(scene.frames.tolist()):
        detections = scene.detections[index][camera_index]
        for (x0, _, x1, y1), person in zip(
            detections.xyxy, detections.object_id.tolist(), strict=True
        ):
            key = (int(frame), int(person))
            if key in positions:
                pixels.append([(x0 + x1) / 2.0, y1])
                world.append(positions[key])
    return np.array(pixels).reshape(-1, 2), np.array(world).reshape(-1, 2)


def predicted_and_real(fit: Any, pixels: np.ndarray, world: np.ndarray) -> np.ndarray:
    """(M, 2): each box's predicted ground error under the fit and its real one (the fitted
    camera locating its bottom centre, against the annotated position), metres."""
    located, _ = fit.camera.pixel_to_world(pixels)
    real = np.hypot(*(located - world).T)
    return np.column_stack([fit.predicted_error_m(pixels), real])


def _predicted_bins(pairs: np.ndarray) -> list[dict[str, Any]]:
    """Share of boxes and their median real error per bin of predicted error."""
    usable = pairs[np.isfinite(pairs).all(axis=1)]
    bins = []
    for low, high in itertools.pairwise(PREDICTED_BINS):
        inside = usable[(usable[:, 0] >= low) & (usable[:, 0] < high)]
        bins.append(
            {
                "low_m": low,
                "high_m": high,
                "share": float(len(inside) / max(len(usable), 1)),
                "real_median_m": float(np.median(inside[:, 1])) if len(inside) else None,
            }
        )
    return bins


def _run(scene: Scene, references: list, positions: dict[str, Any]) -> dict[str, Any]:
    result = track_scene(scene, references=references, camera_positions=positions)
    metrics = evaluate(scene.ground_truth, result.tracks).to_dict()
    errors = localisation_errors(scene, references)
    return {
        "scores": {key: float(metrics[key]) for key in SCORES},
        "median_error_m": float(np.median(errors)),
        "p95_error_m": float(np.percentile(errors, 95)),
        "located": len(errors),
    }


def run_calibration(
    scene: Scene,
    setup: CalibrationSetup = CalibrationSetup(),
    progress: bool = False,
    sites: dict[tuple[int, int], Any] | None = None,
) -> dict[str, Any]:
    """Clicked calibrations vs the lab calibration on one scene.

    Args:
        sites: when given, filled with each run's site, ``(count, seed) -> Site`` (its cameras
            fitted), for :func:`calibration_figure` to draw without fitting them again.

    Returns:
        JSON-ready ``{"setup", "lab", "runs": [...], "rows": [...]}``: ``runs`` has one entry per
        (N, seed) with every camera's fit; ``rows`` one per N (means over the seeds).
    """

    started = time.perf_counter()
    lab = _run(scene, render_scene_references(scene), camera_positions(scene))
    boxes = [box_pixels(scene, index) for index in range(len(scene.cameras))]
    pairs: dict[int, list[np.ndarray]] = {count: [] for count in setup.counts}
    runs = []
    jobs = [(count, seed) for count in setup.counts for seed in setup.seeds]
    iterator: Any = jobs
    if progress:

        iterator = tqdm(jobs, desc="calibrations", leave=False)
    for count, seed in iterator:
        document = clicked_site(scene, count, seed, setup)
        refused = document.pop("refused")
        site = site_from_document(document, None)
        site_scene = site.scene(scene)
        references = [site.render_reference(name) for name in scene.camera_names]
        cameras = site.cameras()
        if sites is not None:
            sites[(count, seed)] = site
        run = _run(site_scene, references, site.camera_positions())
        for camera, (pixels, world) in zip(cameras, boxes, strict=True):
            if camera.fit is not None:
                pairs[count].append(predicted_and_real(camera.fit, pixels, world))
        run.update(
            count=count,
            seed=seed,
            cameras=[_camera_summary(camera, refused[camera.name]) for camera in cameras],
        )
        runs.append(run)
    rows = []
    for count in setup.counts:
        chosen = [run for run in runs if run["count"] == count]
        hota = [run["scores"]["HOTA"] for run in chosen]
        models: dict[str, int] = {}
        for run in chosen:
            for camera in run["cameras"]:
                models[camera["model"]] = models.get(camera["model"], 0) + 1
        rows.append(
            {
                "count": count,
                "models": models,
                "rms_px": float(np.median([c["rms_px"] for r in chosen for c in r["cameras"]])),
                "held_out_m": _median_of([c["held_out_m"] for r in chosen for c in r["cameras"]]),
                "poorly_constrained": int(
                    sum(c["poorly_constrained"] for r in chosen for c in r["cameras"])
                ),
                "median_error_m": float(np.mean([run["median_error_m"] for run in chosen])),
                "p95_error_m": float(np.mean([run["p95_error_m"] for run in chosen])),
                "scores": {
                    key: float(np.mean([run["scores"][key] for run in chosen])) for key in SCORES
                },
                "hota_min": float(min(hota)),
                "hota_max": float(max(hota)),
                "hota_vs_lab": float(np.mean(hota)) - lab["scores"]["HOTA"],
                "positions": float(
                    np.mean([sum(c["position"] is not None for c in r["cameras"]) for r in chosen])
                ),
                "cameras": len(scene.cameras),
                "refused_sets": int(sum(c["refused_sets"] for r in chosen for c in r["cameras"])),
                "predicted_bins": _predicted_bins(np.concatenate(pairs[count])),
            }
        )
    return json_ready(
        {
            "scene": scene.name,
            "frames": len(scene.frames),
            "setup": {
                "counts": list(setup.counts),
                "seeds": list(setup.seeds),
                "noise_px": setup.noise_px,
                "point_frames": setup.point_frames,
                "click_px": setup.click_px,
                "ground_m": setup.ground_m,
            },
            "lab": lab,
            "runs": runs,
            "rows": rows,
            "seconds": time.perf_counter() - started,
        }
    )


def _camera_summary(camera: Any, refused: int) -> dict[str, Any]:
    fit = camera.fit
    chosen = fit.held_out.get(fit.model.value)
    coverage = fit.coverage
    return {
        "name": camera.name,
        "model": fit.model.value,
        "inliers": int(fit.inliers.sum()),
        "rms_px": fit.rms_px,
        "focal_px": fit.focal_px,
        "k1": float(fit.camera.distortion[0]) if fit.camera.has_distortion else 0.0,
        "position": list(camera.position) if camera.position else None,
        "held_out": {
            model: {"score": result.score, "median_m": _median_of(result.error_m.tolist())}
            for model, result in fit.held_out.items()
        },
        # The chosen model's median ground error on points left out of its fit.
        "held_out_m": None if chosen is None else _median_of(chosen.error_m.tolist()),
        "predicted_median_m": None if coverage is None else coverage.median_m,
        "poorly_constrained": any("predicted ground error exceeds" in w for w in fit.warnings),
        "warnings": list(fit.warnings),
        "refused_sets": refused,
    }


def _median_of(values: list[Any]) -> float | None:
    finite = [float(value) for value in values if value is not None and np.isfinite(value)]
    return float(np.median(finite)) if finite else None


def calibration_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`run_calibration`."""
    setup = result["setup"]
    lab = result["lab"]
    lines = [
        f"### Clicked calibration vs lab calibration ({result['scene']}, {result['frames']} "
        f"frames, {len(result['rows'][0]['models']) and result['rows'][0]['cameras']} cameras)",
        "",
        f"Per camera N points (box bottom centres <-> annotated positions from "
        f"{setup['point_frames']} frames, spread over the image, + {setup['noise_px']:g} px "
        f"click noise; the site states {setup.get('click_px', 2.0):g} px clicks and "
        f"{setup.get('ground_m', 0.1):g} m on the ground), "
        f"seeds {', '.join(str(seed) for seed in setup['seeds'])}; "
        "scores are means over the seeds. Command: `cblrs experiment calibration`.",
        "",
        "| points per camera | models chosen | RMS px | held-out m | located error median m "
        "| p95 m | HOTA (min..max) | HOTA - lab | AssA | LocA | IDF1 | cameras with position "
        "| warned: poorly constrained |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        f"| lab calibration | K, R, t | - | - | {lab['median_error_m']:.3f} | "
        f"{lab['p95_error_m']:.3f} | {lab['scores']['HOTA']:.2f} | 0 | "
        f"{lab['scores']['AssA']:.2f} | {lab['scores']['LocA']:.2f} | "
        f"{lab['scores']['IDF1']:.2f} | {result['rows'][0]['cameras']} | - |",
    ]
    for row in result["rows"]:
        models = ", ".join(f"{name} x{count}" for name, count in sorted(row["models"].items()))
        scores = row["scores"]
        held_out = row.get("held_out_m")
        fits = len(result["setup"]["seeds"]) * row["cameras"]
        lines.append(
            f"| {row['count']} | {models} | {row['rms_px']:.1f} | "
            f"{'-' if held_out is None else f'{held_out:.3f}'} | {row['median_error_m']:.3f} | "
            f"{row['p95_error_m']:.3f} | {scores['HOTA']:.2f} ({row['hota_min']:.2f}.."
            f"{row['hota_max']:.2f}) | {row['hota_vs_lab']:+.2f} | {scores['AssA']:.2f} | "
            f"{scores['LocA']:.2f} | {scores['IDF1']:.2f} | {row['positions']:.1f} | "
            f"{row.get('poorly_constrained', 0)} of {fits} |"
        )
    lines += [
        "",
        "Models chosen: counts of camera fits over all seeds (`auto`: of the models the points "
        "allow, the simplest whose cross-validated error on held-out points is within one "
        "standard error of the best). RMS px: median over the fits of each fit's RMS error on "
        "its own points (the fits weigh each point's pixel error against its ground error, "
        "so near points keep larger pixel errors). Held-out m: median over the fits of the "
        "chosen model's median ground error on points left out of its fit (what `cblrs "
        "calibrate` reports). Located error: every annotated box's target pixel read through "
        "the rendered reference, against its annotated position. Warned: fits that warn that "
        "part of the image between the points has a predicted ground error over 0.5 m.",
    ]
    if all("predicted_bins" in row for row in result["rows"]):
        bins = result["rows"][0]["predicted_bins"]
        names = [
            f"{item['low_m']:g}-{item['high_m']:g} m"
            if item["high_m"] is not None and math.isfinite(item["high_m"])
            else f"over {item['low_m']:g} m"
            for item in bins
        ]
        lines += [
            "",
            "Is the predicted error honest? Every annotated box, by the ground error its clicked "
            "calibration predicts at its bottom centre: the share of boxes, and their median real "
            "error (the fitted camera locating the bottom centre, against the annotated position).",
            "",
            "| points per camera | " + " | ".join(f"predicted {name}" for name in names) + " |",
            "|---|" + "---|" * len(names),
        ]
        for row in result["rows"]:
            cells = [
                f"{item['share']:.0%}: {item['real_median_m']:.2f} m"
                if item["real_median_m"] is not None
                else f"{item['share']:.0%}: -"
                for item in row["predicted_bins"]
            ]
            lines.append(f"| {row['count']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def calibration_figure(
    scene: Scene,
    setup: CalibrationSetup,
    folder: Any,
    sites: dict[tuple[int, int], Any] | None = None,
) -> Any:
    """``calibration_clicked.png``: one clicked calibration (10 points or the largest count
    below it, first seed) drawn by :func:`cblrs.viz.calibration.calibration_picture` on a grey
    canvas (WILDTRACK ships no frames): the camera whose fit leaves the largest part of the
    image between its points poorly constrained, to show the shading and the warning.

    ``sites``: those :func:`run_calibration` filled; that run's site is drawn as it was
    fitted there (the points are seeded: fitting them again gives the same site)."""

    count = max([n for n in setup.counts if n <= 10] or [min(setup.counts)])
    site = (sites or {}).get((count, setup.seeds[0]))
    if site is None:
        document = clicked_site(scene, count, setup.seeds[0], setup)
        document.pop("refused")
        site = site_from_document(document, None)
    fits = [site.camera(name).fit for name in scene.camera_names]
    fit = max(
        (fit for fit in fits if fit is not None),
        key=lambda fit: fit.coverage.share if fit.coverage is not None else 0.0,
    )
    path = Path(folder) / "calibration_clicked.png"
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    image = cv2.resize(calibration_picture(fit, None), (960, 540), interpolation=cv2.INTER_AREA)
    return save_image(path, np.asarray(image, dtype=np.uint8))
