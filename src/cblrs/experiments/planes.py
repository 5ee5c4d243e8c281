"""``cblrs experiment planes``: identities and origin-destination across the planes of a city.

The synthetic street of :mod:`cblrs.datasets.city` (four planes, 16 cameras, two overlaps
and a portal) is tracked plane by plane, each plane by its own fusion tracker on its own
cameras, exactly as its matcher would; then:

* **single plane** — each plane's tracks against that plane's ground truth (objects its
  cameras have in view on it): what a matcher alone achieves. Pooled over the planes the way
  TrackEval combines sequences (IDTP, IDFP, IDFN summed);
* **unlinked** — the planes' tracks side by side under distinct ids, against the site's
  ground truth (every object keeps one id on every plane): what a site without linking gets;
* **linked** — the same tracks through :func:`~cblrs.linking.linker.link_tracks`, against the
  site's ground truth.

Scores are TrackEval's under the AI City 2024 protocol (:mod:`cblrs.evaluation.metrics`:
rows keyed by frame and id, similarity ``max(0, 1 - d / 2 m)``, IDF1 matched at 1 m). The
target: linked IDF1 >= 95 % of the single-plane figure. Origin-destination: the site's
analytics (lives that span the portal) on the linked tracks against the same analytics on
the site's ground truth, error = sum over the OD matrix of |predicted - true| / sum of true
(target <= 5 %); the ground truth's OD is checked against the trips the world was built with.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets.city import CityScenes, city_scenes, street_world
from cblrs.datasets.simulate import simulate_detections
from cblrs.detections import Tracks
from cblrs.evaluation.metrics import MATCH_THRESHOLD, build_trackeval_data, evaluate
from cblrs.experiments.counts import count_errors
from cblrs.linking.files import site_analytics_config
from cblrs.linking.linker import link_tracks
from cblrs.pipeline import track_scene

PROTOCOL = (
    "TrackEval (HOTA, Identity) under the AI City 2024 protocol: every camera's rows keyed by "
    "(frame, id), similarity max(0, 1 - d / 2 m), IDF1 matched at 1 m; single plane = each "
    "plane's tracks against its own ground truth, pooled over the planes (IDTP, IDFP, IDFN "
    "summed, as TrackEval combines sequences)"
)


@dataclass(frozen=True)
class PlanesSetup:
    """What the experiment runs.

    Attributes:
        seed: the world's seed.
        detector_seeds: seeds of the simulated detector (``drop`` and ``jitter``), after
            the exact boxes.
        drop, jitter: the simulated detector (see :func:`simulate_detections`).
        people, cars, wanderers, spawn_s, max_trip_m, fps: the world (see
            :func:`street_world`).
    """

    seed: int = 0
    detector_seeds: tuple[int, ...] = (1, 2, 3)
    drop: float = 0.2
    jitter: float = 0.05
    people: int = 40
    cars: int = 12
    wanderers: int = 4
    spawn_s: float = 40.0
    max_trip_m: float = 110.0
    fps: float = 10.0


def pooled_idf1(per_plane: dict[int, tuple[Tracks, Tracks]]) -> float:
    """IDF1 (percent) of several planes' tracks against their own truths, pooled as TrackEval
    combines sequences. ``per_plane``: plane -> (ground truth, tracks)."""
    # lazy: TrackEval takes ~0.4 s to import; only scoring needs it
    from trackeval.metrics import Identity

    identity = Identity({"THRESHOLD": MATCH_THRESHOLD, "PRINT_CONFIG": False})
    sequences = {str(plane): identity.eval_sequence(build_trackeval_data(truth, tracks))
                 for plane, (truth, tracks) in per_plane.items()}
    return 100.0 * float(identity.combine_sequences(sequences)["IDF1"])


def distinct_ids(per_plane: dict[int, Tracks]) -> Tracks:
    """The planes' tracks side by side, each plane's ids made distinct from the others'."""
    offset = 0
    parts = []
    for _, tracks in sorted(per_plane.items()):
        parts.append(replace(tracks, track_id=tracks.track_id + offset))
        offset += int(tracks.track_id.max()) + 1 if len(tracks) else 0
    return Tracks.concatenate(parts)


def run_case(city: CityScenes, detector: str, seed: int | None, setup: PlanesSetup
             ) -> dict[str, Any]:
    """One detector setting through every plane's tracker, the linker and the scoring."""
    started = time.perf_counter()
    tracked: dict[int, Tracks] = {}
    single = {}
    for plane_id, scene in city.planes.items():
        if seed is not None:
            scene = simulate_detections(scene, setup.drop, setup.jitter, seed=seed)
        tracked[plane_id] = track_scene(scene).tracks
        single[plane_id] = (scene.ground_truth, tracked[plane_id])
    per_plane = {plane: evaluate(truth, tracks).to_dict()
                 for plane, (truth, tracks) in single.items()}
    single_idf1 = pooled_idf1(single)
    unlinked = evaluate(city.ground_truth, distinct_ids(tracked))
    linked_rows, handovers, counters = link_tracks(city.spec.planes, city.spec.links, tracked)
    linked = evaluate(city.ground_truth, linked_rows.tracks)
    config = site_analytics_config(city.spec.links)
    truth_counts = analyse_tracks(city.ground_truth, city.spec.places, config)
    linked_counts = count_errors(truth_counts,
                                 analyse_tracks(linked_rows.tracks, city.spec.places, config))
    unlinked_counts = count_errors(truth_counts, analyse_tracks(distinct_ids(tracked),
                                                                city.spec.places, config))
    kinds: dict[str, int] = {}
    for item in handovers:
        kinds[item.kind] = kinds.get(item.kind, 0) + 1
    return {
        "detector": detector,
        "single_plane": {"idf1_pooled": single_idf1, "per_plane": per_plane},
        "unlinked": unlinked.to_dict() | {"ids": unlinked.num_predicted_ids},
        "linked": linked.to_dict() | {"ids": linked.num_predicted_ids},
        "true_ids": linked.num_gt_ids,
        "ratio": linked.IDF1 / single_idf1 if single_idf1 > 0 else math.nan,
        "handovers": kinds,
        "late_rows": counters.get("late_rows", 0),
        "od_error": linked_counts["od_error"],
        "unlinked_od_error": unlinked_counts["od_error"],
        "line_error": linked_counts["line_error"],
        "entry_error": linked_counts["entry_error"],
        "seconds": time.perf_counter() - started,
    }


def run_planes(setup: PlanesSetup, report: Callable[[str], None] | None = None
               ) -> dict[str, Any]:
    """Build the city, run every detector setting, return the figures (JSON-ready)."""
    spec = street_world(setup.seed, people=setup.people, cars=setup.cars,
                        wanderers=setup.wanderers, spawn_s=setup.spawn_s,
                        max_trip_m=setup.max_trip_m, fps=setup.fps)
    city = city_scenes(spec)
    truth = analyse_tracks(city.ground_truth, spec.places, site_analytics_config(spec.links))
    counted = {(origin, destination): value for origin, row in truth.od.items()
               for destination, value in row.items() if value}
    planes_of: dict[int, set[int]] = {}
    for plane_id, scene in city.planes.items():
        for object_id in np.unique(scene.ground_truth.track_id).tolist():
            planes_of.setdefault(object_id, set()).add(plane_id)
    world = {
        "planes": len(spec.planes), "cameras": city.camera_count,
        "objects": len(spec.world.objects), "trips": len(spec.trips),
        "seconds": round(spec.world.duration_s, 1), "frames": len(city.timestamps),
        "objects_on_several_planes": sum(len(planes) > 1 for planes in planes_of.values()),
        "objects_through_the_portal": sum({3, 4} <= planes for planes in planes_of.values()),
        "od_trips_counted": sum(counted.values()),
        "truth_od_equals_built": counted == dict(spec.true_od()),
    }
    cases = []
    settings: list[tuple[str, int | None]] = [("exact", None)]
    settings += [(f"--drop {setup.drop:g} --jitter {setup.jitter:g} --seed {seed}", seed)
                 for seed in setup.detector_seeds]
    for detector, seed in settings:
        case = run_case(city, detector, seed, setup)
        cases.append(case)
        if report is not None:
            report(f"{detector}: single {case['single_plane']['idf1_pooled']:.2f}, linked "
                   f"{case['linked']['IDF1']:.2f} ({100 * case['ratio']:.1f} %), OD error "
                   f"{100 * case['od_error']:.1f} %")
    return {"setup": asdict(setup), "protocol": PROTOCOL, "world": world, "cases": cases}


def _percent(value: float) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{100 * value:.1f} %"


def planes_report(result: dict[str, Any]) -> str:
    """The experiment's markdown tables."""
    world, setup = result["world"], result["setup"]
    lines = [
        "### Identities and origin-destination across planes (synthetic street, "
        f"{world['planes']} planes, {world['cameras']} cameras)",
        "",
        f"World: seed {setup['seed']}, {world['objects']} objects ({world['trips']} with an "
        f"origin and a destination), {world['seconds']} s at {setup['fps']:g} fps; "
        f"{world['objects_on_several_planes']} objects are seen on more than one plane, "
        f"{world['objects_through_the_portal']} pass the unseen stretch between planes 3 and 4; "
        f"the ground truth's OD counts {world['od_trips_counted']} trips and equals the built "
        f"one: {'yes' if world['truth_od_equals_built'] else 'NO'}. Scoring: "
        f"{result['protocol']}. Command: `cblrs experiment planes`.",
        "",
        "| detector | single-plane IDF1 | unlinked IDF1 | linked IDF1 | linked / single | "
        "linked HOTA | ids linked / true | hand-overs overlap / portal | OD error linked | "
        "OD error unlinked | line error | entry error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in result["cases"]:
        handovers = case["handovers"]
        lines.append(
            f"| {case['detector']} | {case['single_plane']['idf1_pooled']:.2f} | "
            f"{case['unlinked']['IDF1']:.2f} | {case['linked']['IDF1']:.2f} | "
            f"{100 * case['ratio']:.1f} % | {case['linked']['HOTA']:.2f} | "
            f"{case['linked']['ids']} / {case['true_ids']} | "
            f"{handovers.get('overlap', 0)} / {handovers.get('portal', 0)} | "
            f"{_percent(case['od_error'])} | {_percent(case['unlinked_od_error'])} | "
            f"{_percent(case['line_error'])} | {_percent(case['entry_error'])} |"
        )
    lines += ["", "Per plane (each against its own ground truth), IDF1:", "",
              "| detector | " + " | ".join(f"plane {plane}" for plane in
                                            result["cases"][0]["single_plane"]["per_plane"])
              + " |",
              "|---|" + "---|" * len(result["cases"][0]["single_plane"]["per_plane"])]
    for case in result["cases"]:
        per_plane = case["single_plane"]["per_plane"]
        lines.append(f"| {case['detector']} | "
                     + " | ".join(f"{scores['IDF1']:.2f}" for scores in per_plane.values())
                     + " |")
    return "\n".join(lines) + "\n"
