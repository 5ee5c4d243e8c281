"""Identity where it is hard: the tracking cases of issue 19, scored in one table.

Each case is a scene (traffic at a roundabout or a crossroads, a dense crowd, people seen
through distorting lenses, WILDTRACK, MultiviewX from its images) tracked by ``fusion`` with
its defaults, from one kind of boxes:

* ``exact``: the scene's own boxes (annotations, or the synthetic world's projections);
* ``sim``: the simulated detector of ``cblrs track --drop 0.2 --jitter 0.05 --seed S``;
* ``real``: :func:`cblrs.datasets.detector_model.realistic_detections` (misses that follow
  occlusion and distance and persist, truncated boxes, persistent false positives);
* ``yolox``: the shipped YOLOX-Nano run on the data set's images (MultiviewX).

Scores: HOTA and AssA under the AI City protocol, MOTA and IDF1 at 1 m (the match distance of
the published multi-view trackers), identities predicted vs true, and, where the scene has a
site file with places, the line-count error and the origin-destination error of the
analytics against the same analytics on the ground truth
(:func:`cblrs.experiments.counts.count_errors`). Cases marked *held out* are checks the
tracker was not tuned on. Nothing here is tuned to a case: every run uses the defaults.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.site import load_site_places
from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets import simulate_detections
from cblrs.datasets.detector_model import realistic_detections
from cblrs.datasets.scene import Scene
from cblrs.errors import DatasetError
from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.counts import count_errors, find_sites
from cblrs.pipeline import render_scene_references, track_scene

logger = logging.getLogger(__name__)

PUBLISHED = (
    ("MVTrajecter (ICCV 2025)", "WILDTRACK test frames, learned detector trained on WILDTRACK",
     94.3, 96.5),
    ("MV3DT (2026)", "WILDTRACK, calibrated cameras over MQTT, no training on WILDTRACK",
     93.1, 96.5),
    ("ReST", "WILDTRACK test frames 1800-1995, the real multi-view detector's output", None,
     86.0),
)
"""Published multi-view trackers on WILDTRACK: (name, input, MOTA, IDF1), as issue 19 cites
them (MOTA / IDF1 at 1 m)."""


@dataclass(frozen=True)
class Case:
    """One scene with one kind of boxes.

    Attributes:
        scene: ``roundabout``, ``crossroads``, ``crowd``, ``distorted``, ``wildtrack`` or
            ``multiviewx``.
        seed: the scene's seed (synthetic worlds).
        size: cars (roundabout) or people (crowd, distorted); 0 for the scene's default.
        boxes: ``exact``, ``sim``, ``real`` or ``yolox``.
        box_seed: seed of the simulated detector.
        held_out: a check the tracker was not tuned on.
        target: the issue's target, e.g. ``{"HOTA": 90, "od_error": 0.05, "ids_equal": 1}``.
    """

    scene: str
    seed: int = 0
    size: int = 0
    boxes: str = "exact"
    box_seed: int = 1
    held_out: bool = False
    target: tuple[tuple[str, float], ...] = ()

    @property
    def scene_label(self) -> str:
        """The scene with its seed and size, e.g. ``roundabout 40 cars, seed 1``."""
        if self.scene in ("wildtrack", "multiviewx"):
            return self.scene
        unit = "cars" if self.scene == "roundabout" else "people"
        size = f" {self.size} {unit}" if self.size else ""
        return f"{self.scene}{size}, seed {self.seed}"

    @property
    def boxes_label(self) -> str:
        """The kind of boxes, with the simulated detector's seed."""
        if self.boxes == "sim":
            return f"sim drop 0.2 jitter 0.05 seed {self.box_seed}"
        if self.boxes == "real":
            return f"realistic detector seed {self.box_seed}"
        if self.boxes == "yolox":
            return "YOLOX-Nano on the images"
        return "exact"


_TRAFFIC = (("ids_equal", 1.0), ("od_error", 0.05), ("HOTA", 90.0))
_CROWD = (("HOTA", 85.0),)
_DISTORTED = (("HOTA", 90.0), ("ids_at_most", 44.0))
_WILDTRACK_SIM = (("line_error", 0.02),)


def default_cases() -> tuple[Case, ...]:
    """The issue's cases, then the held-out checks."""
    cases: list[Case] = []
    for seed, cars in ((1, 40), (2, 50), (3, 60)):
        cases.append(Case("roundabout", seed, cars, "exact", target=_TRAFFIC))
        cases.append(Case("roundabout", seed, cars, "sim", seed, target=_TRAFFIC))
    cases.append(Case("roundabout", 0, 30, "exact", target=_TRAFFIC))
    cases.append(Case("roundabout", 0, 30, "sim", 1, target=_TRAFFIC))
    cases.append(Case("crowd", 1, 60, "exact", target=_CROWD))
    cases.append(Case("distorted", 1, 40, "exact", target=_DISTORTED))
    cases.append(Case("multiviewx", boxes="yolox", target=(("HOTA", 85.0),)))
    cases.append(Case("wildtrack", boxes="exact"))
    for seed in (1, 2, 3):
        cases.append(Case("wildtrack", boxes="sim", box_seed=seed, target=_WILDTRACK_SIM))
    # Held out: not tuned on.
    cases.append(Case("crossroads", 1, 0, "exact", held_out=True, target=_TRAFFIC))
    cases.append(Case("crossroads", 2, 0, "sim", 2, held_out=True, target=_TRAFFIC))
    cases.append(Case("crossroads", 3, 0, "real", 3, held_out=True, target=_TRAFFIC))
    cases.append(Case("crowd", 2, 60, "real", 2, held_out=True))
    cases.append(Case("wildtrack", boxes="real", box_seed=1, held_out=True))
    cases.append(Case("roundabout", 4, 50, "real", 4, held_out=True, target=_TRAFFIC))
    return tuple(cases)


WITHOUT_RULES: tuple[tuple[str, Any], ...] = (
    ("end_off_plane", False), ("class_turn_radius_m", {}), ("confirm_cameras", 1),
    ("stitch_gap_s", 0.0))
"""Fusion options that turn off issue 19's rules (tracks leaving the plane end, vehicles
cannot turn on the spot, multi-view confirmation, stitching a new track to a lost one): the
tracker as it was before them."""

SCENES = ("roundabout", "crossroads", "crowd", "distorted", "wildtrack", "multiviewx")


@dataclass(frozen=True)
class TrackingSetup:
    """What :func:`run_tracking` measures.

    Attributes:
        cases: the cases (default :func:`default_cases`).
        wildtrack, multiviewx: data folders (None: ``../shared/data/...``).
        model: the ONNX model of ``yolox`` cases (None: ``../shared/models/yolox_nano.onnx``).
        sites: folder of site files (None: the repository's ``sites/``).
        matcher_options: fusion options instead of the defaults (e.g. :data:`WITHOUT_RULES`).
    """

    cases: tuple[Case, ...] = ()
    wildtrack: Path | None = None
    multiviewx: Path | None = None
    model: Path | None = None
    sites: Path | None = None
    matcher_options: tuple[tuple[str, Any], ...] = ()


def _data(path: Path | None, name: str) -> Path:
    """The data folder: given, else ``$CBLRS_<NAME>``, else ``../shared/data/<name>``."""
    default = os.environ.get(f"CBLRS_{name.upper()}") or Path("../shared/data") / name
    found = path if path is not None else Path(default)
    if not found.is_dir():
        raise DatasetError(f"{name} not found at {found}; pass its folder.")
    return found


def build_scene(case: Case, setup: TrackingSetup) -> Scene:
    """The case's scene with its exact boxes (for ``yolox``: the annotated scene)."""
    # lazy: each world pulls its own generator; a run needs only the ones it scores
    if case.scene == "roundabout":
        from cblrs.datasets.synthetic import SyntheticWorld
        from cblrs.datasets.traffic import roundabout_traffic_world

        return SyntheticWorld(roundabout_traffic_world(case.seed, cars=case.size or 30)).scene()
    if case.scene == "crossroads":
        from cblrs.datasets.crossroads import make_crossroads_scene

        return make_crossroads_scene(case.seed)
    if case.scene == "crowd":
        from cblrs.datasets.crowds import make_crowd_scene

        return make_crowd_scene(_data(setup.wildtrack, "wildtrack"), case.seed, case.size or 60)
    if case.scene == "distorted":
        from cblrs.datasets.crowds import make_distorted_scene

        return make_distorted_scene(case.seed, case.size or 40)
    if case.scene in ("wildtrack", "multiviewx"):
        from cblrs.datasets import load_scene

        folder = setup.wildtrack if case.scene == "wildtrack" else setup.multiviewx
        return load_scene(_data(folder, case.scene))
    raise DatasetError(f"unknown scene {case.scene!r}; known: {', '.join(SCENES)}.")


def boxes_of(case: Case, scene: Scene, references: list, setup: TrackingSetup) -> Scene:
    """The scene with the case's kind of boxes."""
    if case.boxes == "exact":
        return scene
    if case.boxes == "sim":
        return simulate_detections(scene, drop=0.2, jitter=0.05, seed=case.box_seed)
    if case.boxes == "real":
        return realistic_detections(scene, seed=case.box_seed)
    if case.boxes == "yolox":
        from cblrs.detectors.offline import detect_scene

        model = setup.model or Path("../shared/models/yolox_nano.onnx")
        if not model.is_file():
            raise DatasetError(f"model not found at {model}; pass --model.")
        folder = _data(setup.multiviewx if case.scene == "multiviewx" else setup.wildtrack,
                       case.scene)
        return detect_scene(scene, folder, model, references).scene
    raise DatasetError(f"unknown kind of boxes {case.boxes!r}.")


def _area(case: Case, setup: TrackingSetup) -> tuple[float, float, float, float] | None:
    if case.scene not in ("wildtrack", "multiviewx"):
        return None
    from cblrs.calibration import default_ground

    folder = setup.wildtrack if case.scene == "wildtrack" else setup.multiviewx
    return default_ground(_data(folder, case.scene))


def run_case(case: Case, scene: Scene, references: list, setup: TrackingSetup) -> dict[str, Any]:
    """Track one case with the defaults and score it (JSON-ready)."""
    started = time.perf_counter()
    variant = boxes_of(case, scene, references, setup)
    # As ``cblrs track`` does by default: a detector's boxes end where a person is hidden,
    # so a foot point inside a nearer box is not located (annotated boxes keep theirs).
    detector = case.boxes in ("real", "yolox")
    tracks = track_scene(variant, references=references, drop_hidden_feet=detector,
                         **dict(setup.matcher_options)).tracks
    metrics = evaluate(scene.ground_truth, tracks, area=_area(case, setup))
    row: dict[str, Any] = {
        "scene": case.scene_label, "boxes": case.boxes_label, "held_out": case.held_out,
        "HOTA": metrics.HOTA, "AssA": metrics.AssA, "DetA": metrics.DetA,
        "IDF1": metrics.IDF1, "MOTA": metrics.MOTA, "IDSW": metrics.IDSW,
        "predicted_ids": len(np.unique(tracks.track_id)),
        "true_ids": len(np.unique(scene.ground_truth.track_id)),
        "line_error": math.nan, "od_error": math.nan,
    }
    site_name = {"roundabout": "roundabout-traffic"}.get(case.scene, case.scene)
    site_file = find_sites(setup.sites) / f"{site_name}.yaml"
    if site_file.is_file():
        places = load_site_places(site_file).places
        errors = count_errors(analyse_tracks(scene.ground_truth, places),
                              analyse_tracks(tracks, places))
        row["line_error"], row["od_error"] = errors["line_error"], errors["od_error"]
    for key in ("line_error", "od_error"):
        if not math.isfinite(row[key]):
            row[key] = None  # no such places (JSON has no NaN)
    row["seconds"] = time.perf_counter() - started
    row["target"] = dict(case.target)
    row["met"] = target_met(row, case.target)
    return row


def target_met(row: dict[str, Any], target: tuple[tuple[str, float], ...]) -> bool | None:
    """Whether a row meets its case's target (None: the case has none)."""
    if not target:
        return None
    met = True
    for key, value in target:
        if key == "ids_equal":
            met &= row["predicted_ids"] == row["true_ids"]
        elif key == "ids_at_most":
            met &= row["predicted_ids"] <= value
        elif key in ("od_error", "line_error"):
            met &= row[key] is not None and row[key] <= value + 1e-12
        else:
            met &= row[key] >= value
    return bool(met)


def _scene_groups(cases: tuple[Case, ...]) -> list[tuple[Case, ...]]:
    """The cases in runs of one scene (same scene, seed and size), in their order."""
    groups: list[list[Case]] = []
    for case in cases:
        if groups and (groups[-1][0].scene, groups[-1][0].seed, groups[-1][0].size) == (
                case.scene, case.seed, case.size):
            groups[-1].append(case)
        else:
            groups.append([case])
    return [tuple(group) for group in groups]


def _run_group(group: tuple[Case, ...], setup: TrackingSetup) -> list[dict[str, Any]]:
    """The rows of one scene's cases: the scene and its references are built once."""
    scene = build_scene(group[0], setup)
    references = render_scene_references(scene)
    return [run_case(case, scene, references, setup) for case in group]


def run_tracking(
    setup: TrackingSetup, report: Callable[[str], None] | None = None, jobs: int = 1
) -> dict[str, Any]:
    """Run every case; scenes and reference images are built once per scene.

    Args:
        jobs: scenes tracked at once, each in its own process (1: all in this one). The
            cases are independent and seeded, so the rows do not depend on it; only the
            ``seconds`` of each row do (cases running side by side share the cores).

    Returns:
        ``{"rows": [...], "published": [...]}`` (JSON-ready), rows in the cases' order.
    """
    cases = setup.cases or default_cases()
    groups = _scene_groups(cases)

    def done(rows: list[dict[str, Any]]) -> None:
        for row in rows:
            if report is not None:
                report(f"{row['scene']} / {row['boxes']}: HOTA {row['HOTA']:.1f}, ids "
                       f"{row['predicted_ids']} / {row['true_ids']} ({row['seconds']:.0f} s)")

    results: list[list[dict[str, Any]]] = []
    if jobs <= 1 or len(groups) <= 1:
        for group in groups:
            results.append(_run_group(group, setup))
            done(results[-1])
    else:
        # Processes, not threads: the tracker is Python. "spawn" starts each worker clean
        # (no copy of this process's threads or open files).
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(jobs, len(groups)), mp_context=context) as pool:
            futures = [pool.submit(_run_group, group, setup) for group in groups]
            for future in as_completed(futures):
                done(future.result())
            results = [future.result() for future in futures]
    rows = [row for group_rows in results for row in group_rows]
    published = [{"tracker": name, "input": source, "MOTA": mota, "IDF1": idf1}
                 for name, source, mota, idf1 in PUBLISHED]
    return {"rows": rows, "published": published,
            "matcher_options": {key: value for key, value in setup.matcher_options}}


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def _target_text(target: dict[str, float]) -> str:
    parts = []
    for key, value in target.items():
        if key == "ids_equal":
            parts.append("ids = true")
        elif key == "ids_at_most":
            parts.append(f"ids ≤ {value:g}")
        elif key in ("od_error", "line_error"):
            parts.append(f"{'OD' if key == 'od_error' else 'line'} ≤ {100 * value:g} %")
        else:
            parts.append(f"{key} ≥ {value:g}")
    return ", ".join(parts)


def tracking_report(result: dict[str, Any]) -> str:
    """Markdown tables of :func:`run_tracking`'s result."""
    options = result.get("matcher_options") or {}
    title = "fusion, defaults" if not options else "fusion, " + ", ".join(
        f"{key}={value}" for key, value in options.items())
    text = [
        f"### Identity where it is hard ({title})",
        "",
        "HOTA and AssA: AI City 2024 protocol; MOTA and IDF1 at 1 m; ids: identities "
        "predicted / true; line and OD errors: analytics on the tracks against analytics on "
        "the ground truth (sum of |predicted - true| / sum of true). *Held out*: checks the "
        "tracker was not tuned on. Command: `cblrs experiment tracking"
        + (" --without-rules`." if options else "`."),
        "",
        "| scene | boxes | HOTA | AssA | IDF1 | MOTA | ids | line error | OD error | target "
        "| met |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        scene = f"{row['scene']} (held out)" if row["held_out"] else row["scene"]
        met = {None: "–", True: "yes", False: "**no**"}[row["met"]]
        text.append(
            f"| {scene} | {row['boxes']} | {row['HOTA']:.1f} | {row['AssA']:.1f} | "
            f"{row['IDF1']:.1f} | {row['MOTA']:.1f} | {row['predicted_ids']} / "
            f"{row['true_ids']} | {_percent(row['line_error'])} | {_percent(row['od_error'])} "
            f"| {_target_text(row['target'])} | {met} |"
        )
    text += [
        "",
        "Published multi-view trackers on WILDTRACK (their figures and inputs, MOTA / IDF1 "
        "at 1 m) beside fusion's on WILDTRACK's 200 annotated frames:",
        "",
        "| tracker | input | MOTA | IDF1 |",
        "|---|---|---|---|",
    ]
    for entry in result["published"]:
        mota = "–" if entry["MOTA"] is None else f"{entry['MOTA']:.1f}"
        text.append(f"| {entry['tracker']} | {entry['input']} | {mota} | "
                    f"{'about ' if entry['tracker'] == 'ReST' else ''}{entry['IDF1']:.1f} |")
    for row in result["rows"]:
        if row["scene"] == "wildtrack":
            text.append(f"| cblrs fusion | WILDTRACK frames 0-995, {row['boxes']} boxes "
                        f"(location only, no training) | {row['MOTA']:.1f} | {row['IDF1']:.1f} |")
    return "\n".join(text) + "\n"
