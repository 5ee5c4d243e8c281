"""What a realistic detector costs the tracker: HOTA with one cause of its errors removed.

    python scripts/detector_costs.py roundabout --seed 5 --size 50 --box-seed 5
    python scripts/detector_costs.py wildtrack --box-seed 5 [--option support_ratio=0]

Tracks one scene (as a case of ``cblrs experiment tracking`` does, ``fusion`` defaults unless
``--option`` sets some) with :func:`cblrs.datasets.detector_model.realistic_detections`, then
again with each cause of the detector's errors turned off in turn (truncated boxes, false
positives, misses that follow occlusion and distance and persist, box noise), and prints one
markdown row per variant: HOTA, DetA, AssA, IDF1, MOTA, identity switches, ids.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

import numpy as np

from cblrs.datasets.detector_model import DetectorModel, realistic_detections
from cblrs.errors import DatasetError
from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.tracking import SCENES, Case, TrackingSetup, _area, build_scene
from cblrs.pipeline import render_scene_references, track_scene

VARIANTS = (
    ("nothing (the realistic detector)", {}),
    ("truncated boxes of half-hidden objects", {"truncation": 0.0}),
    ("persistent and transient false positives", {"false_sites": 0, "transient_false": 0.0}),
    (
        "misses that follow occlusion and distance and persist",
        {"occluded_miss": 0.0, "far_miss": 0.0, "persistence": 0.0},
    ),
    ("box noise", {"jitter": 0.0}),
)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", choices=SCENES)
    parser.add_argument("--seed", type=int, default=0, help="the scene's seed")
    parser.add_argument("--size", type=int, default=0, help="cars or people (0: default)")
    parser.add_argument("--box-seed", type=int, default=1, help="the detector model's seed")
    parser.add_argument(
        "--option", action="append", default=[], help="fusion option NAME=JSON_VALUE (repeatable)"
    )
    args = parser.parse_args(argv)
    options = {}
    for text in args.option:
        name, _, value = text.partition("=")
        try:
            options[name] = json.loads(value)
        except json.JSONDecodeError:
            print(f"--option {text!r} is not NAME=JSON_VALUE.", file=sys.stderr)
            return 2
    case = Case(args.scene, args.seed, args.size, "real", args.box_seed)
    setup = TrackingSetup()
    try:
        scene = build_scene(case, setup)
    except DatasetError as error:
        print(error, file=sys.stderr)
        return 2
    references = render_scene_references(scene)
    print(f"{case.scene_label}, {case.boxes_label}; fusion options {options or 'defaults'}")
    print("| removed | HOTA | DetA | AssA | IDF1 | MOTA | IDSW | ids |")
    print("|---|---|---|---|---|---|---|---|")
    for label, change in VARIANTS:
        boxes = realistic_detections(
            scene, seed=case.box_seed, model=replace(DetectorModel(), **change)
        )
        tracks = track_scene(boxes, references=references, drop_hidden_feet=True, **options).tracks
        metrics = evaluate(scene.ground_truth, tracks, area=_area(case, setup))
        print(
            f"| {label} | {metrics.HOTA:.1f} | {metrics.DetA:.1f} | {metrics.AssA:.1f} | "
            f"{metrics.IDF1:.1f} | {metrics.MOTA:.1f} | {metrics.IDSW} | "
            f"{len(np.unique(tracks.track_id))} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
