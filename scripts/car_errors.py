"""Where a roundabout case's positions are off: each reported row against its car, by age.

    python scripts/car_errors.py [--seed 0] [--size 30] [--boxes sim] [--box-seed 1]
                                 [--option vehicle_minimum_sigma_m=0]

Tracks one roundabout case of ``cblrs experiment tracking`` (``fusion`` defaults unless
``--option`` sets some), matches its rows to the ground truth frame by frame (Hungarian,
within 2 m) and prints HOTA, DetA, AssA, LocA, then per car age (seconds since the car's
first ground-truth row) the rows, the rows missed, the mean distance to the footprint
centre and its mean along and across the car's heading (negative along: behind the car).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.optimize import linear_sum_assignment

from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.tracking import Case, TrackingSetup, boxes_of, build_scene
from cblrs.pipeline import render_scene_references, track_scene

AGES = ((0.0, 0.5), (0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, np.inf))


def row_errors(truth, tracks) -> np.ndarray:
    """(G, 4): per ground-truth row its car's age (s), distance to the matched row (inf:
    missed), and that offset along and across the car's heading (metres)."""
    first = {int(c): float(truth.timestamp[truth.track_id == c].min())
             for c in np.unique(truth.track_id)}
    heading = np.zeros_like(truth.world_xy)
    for car in np.unique(truth.track_id):
        rows = np.flatnonzero(truth.track_id == car)
        step = np.gradient(truth.world_xy[rows], axis=0) if len(rows) > 1 else np.zeros((1, 2))
        heading[rows] = step / np.maximum(np.hypot(step[:, 0], step[:, 1]), 1e-9)[:, None]
    out = np.full((len(truth.frame), 4), np.nan)
    out[:, 1] = np.inf
    for frame in np.unique(truth.frame):
        rows = np.flatnonzero(truth.frame == frame)
        out[rows, 0] = truth.timestamp[rows] - [first[int(c)] for c in truth.track_id[rows]]
        predicted = tracks.world_xy[tracks.frame == frame]
        if not len(predicted):
            continue
        offset = predicted[None] - truth.world_xy[rows][:, None]
        distance = np.hypot(offset[..., 0], offset[..., 1])
        matched, columns = linear_sum_assignment(np.where(distance < 2.0, distance, 1e6))
        for row, column in zip(matched, columns, strict=True):
            if distance[row, column] < 2.0:
                ahead = heading[rows[row]]
                vector = offset[row, column]
                out[rows[row], 1:] = (distance[row, column], vector @ ahead,
                                      ahead[0] * vector[1] - ahead[1] * vector[0])
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=30, help="cars")
    parser.add_argument("--boxes", choices=("exact", "sim"), default="sim")
    parser.add_argument("--box-seed", type=int, default=1)
    parser.add_argument("--option", action="append", default=[],
                        help="a fusion option NAME=JSON, e.g. vehicle_minimum_sigma_m=0")
    args = parser.parse_args(argv)
    options = {}
    for text in args.option:
        name, _, value = text.partition("=")
        try:
            options[name] = json.loads(value)
        except json.JSONDecodeError:
            print(f"--option {text!r}: the value must be JSON (a number, true, ...).",
                  file=sys.stderr)
            return 2
    case = Case("roundabout", args.seed, args.size, args.boxes, args.box_seed)
    setup = TrackingSetup()
    scene = build_scene(case, setup)
    references = render_scene_references(scene)
    tracks = track_scene(boxes_of(case, scene, references, setup), references=references,
                         **options).tracks
    metrics = evaluate(scene.ground_truth, tracks)
    print(f"{case.scene_label}, {case.boxes_label}: HOTA {metrics.HOTA:.2f}, DetA "
          f"{metrics.DetA:.2f}, AssA {metrics.AssA:.2f}, LocA {metrics.LocA:.2f}")
    errors = row_errors(scene.ground_truth, tracks)
    print("car age s | rows | missed | mean m | along heading m | across m")
    for low, high in AGES:
        rows = (errors[:, 0] >= low) & (errors[:, 0] < high)
        found = rows & np.isfinite(errors[:, 1])
        if not found.any():
            continue
        print(f"{low:g}-{high:g} | {rows.sum()} | {(rows & ~found).sum()} | "
              f"{errors[found, 1].mean():.3f} | {errors[found, 2].mean():+.3f} | "
              f"{errors[found, 3].mean():+.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
