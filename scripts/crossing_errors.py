"""Which line crossings differ between the tracks and the ground truth, and why.

    python scripts/crossing_errors.py [--seeds 1,2,3] [--drop 0.2] [--jitter 0.05] [--dataset DIR]

Tracks WILDTRACK with the simulated detector (as ``cblrs experiment tracking`` does), runs the
analytics of ``sites/wildtrack.yaml`` on the tracks and on the ground truth, and prints per
seed the line error and every crossing left unmatched by
:func:`cblrs.experiments.counts.match_crossings`' matching (same line and direction, 2 s,
2 m), each with the person (or track) it belongs to and a reason:

* ``truth jumps``: the ground-truth id of that person steps faster than the analytics' speed
  limit within 3 s of the crossing (an annotation error or an annotated identity switch),
  which ends its life there, so the truth counts no crossing;
* ``truth starts in band`` / ``truth ends in band``: the ground-truth id begins or ends
  within the line's hysteresis band, so it has no side to change from or to;
* ``track starts late``: the track following the person is first reported at or after the
  crossing (it was tentative until then);
* ``track ends early``: the track stops before the crossing;
* ``tracks``: anything else (swaps, a track following two people, ...).

A count error is the sum over lines and directions of |predicted - true|: a miss and an
extra of one line and direction cancel in it, so the printout also gives each line's net.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from cblrs.analytics.config import AnalyticsConfig
from cblrs.analytics.site import load_site_places
from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets import load_scene, simulate_detections
from cblrs.experiments.counts import count_errors, find_sites
from cblrs.pipeline import render_scene_references, track_scene


def unmatched(truth, predicted, seconds: float = 2.0, metres: float = 2.0):
    """The crossings of each side left unmatched (as ``match_crossings`` matches them)."""
    missed, extra = [], []
    groups = {(event.line, event.direction)
              for event in truth.crossings + predicted.crossings}
    for line, direction in sorted(groups):
        true = [e for e in truth.crossings if (e.line, e.direction) == (line, direction)]
        found = [e for e in predicted.crossings if (e.line, e.direction) == (line, direction)]
        used_true, used_found = set(), set()
        if true and found:
            gap = np.abs(np.subtract.outer([e.timestamp for e in true],
                                           [e.timestamp for e in found]))
            distance = np.linalg.norm(np.array([e.world_xy for e in true])[:, None]
                                      - np.array([e.world_xy for e in found])[None], axis=2)
            cost = gap / seconds + distance / metres
            cost[(gap > seconds) | (distance > metres)] = 1e6
            for row, column in zip(*linear_sum_assignment(cost), strict=True):
                if cost[row, column] < 1e6:
                    used_true.add(row)
                    used_found.add(column)
        missed += [e for index, e in enumerate(true) if index not in used_true]
        extra += [e for index, e in enumerate(found) if index not in used_found]
    return missed, extra


def rows_of(tracks, track_id):
    """(times, positions) of one id, in time order."""
    rows = np.flatnonzero(tracks.track_id == track_id)
    rows = rows[np.argsort(tracks.timestamp[rows], kind="stable")]
    return tracks.timestamp[rows], tracks.world_xy[rows]


def nearest(tracks, timestamp, xy, radius_m=1.0):
    """The id of ``tracks`` nearest to ``xy`` at the instant nearest ``timestamp`` (or None)."""
    instant = tracks.timestamp[np.argmin(np.abs(tracks.timestamp - timestamp))]
    rows = np.flatnonzero(tracks.timestamp == instant)
    if not len(rows):
        return None
    distance = np.linalg.norm(tracks.world_xy[rows] - xy, axis=1)
    best = int(np.argmin(distance))
    return int(tracks.track_id[rows[best]]) if distance[best] < radius_m else None


def truth_reason(ground_truth, person, line, event, config):
    """Why the ground truth of ``person`` may count no crossing near ``event`` (or None)."""
    times, xy = rows_of(ground_truth, person)
    near = np.abs(times - event.timestamp) <= 3.0
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.maximum(np.diff(times), 1e-9)
    if np.any((speed > config.max_person_speed_m_s) & near[1:] & near[:-1]):
        return "truth jumps"
    normal = np.array([-(line.end[1] - line.start[1]), line.end[0] - line.start[0]], float)
    normal /= np.linalg.norm(normal)
    side = (xy - np.asarray(line.start, float)) @ normal
    band = config.line_hysteresis_m if line.hysteresis_m is None else line.hysteresis_m
    if abs(side[0]) <= band and abs(times[0] - event.timestamp) <= 3.0:
        return "truth starts in band"
    if abs(side[-1]) <= band and abs(times[-1] - event.timestamp) <= 3.0:
        return "truth ends in band"
    return None


def track_reason(tracks, track_id, event):
    """Why the track following a person may count no crossing at ``event`` (or None)."""
    if track_id is None:
        return "no track within 1 m"
    times, _ = rows_of(tracks, track_id)
    if times[0] >= event.timestamp - 0.25:
        return "track starts late"
    if times[-1] <= event.timestamp + 0.25:
        return "track ends early"
    return None


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--drop", type=float, default=0.2)
    parser.add_argument("--jitter", type=float, default=0.05)
    parser.add_argument("--dataset", type=Path, default=Path("../shared/data/wildtrack"))
    args = parser.parse_args(argv)
    scene = load_scene(args.dataset)
    references = render_scene_references(scene)
    places = load_site_places(find_sites() / "wildtrack.yaml").places
    lines = {line.name: line for line in places.lines}
    config = AnalyticsConfig()
    ground_truth = scene.ground_truth
    truth = analyse_tracks(ground_truth, places, config)
    for seed in (int(value) for value in args.seeds.split(",")):
        boxes = simulate_detections(scene, drop=args.drop, jitter=args.jitter, seed=seed)
        tracks = track_scene(boxes, references=references).tracks
        predicted = analyse_tracks(tracks, places, config)
        errors = count_errors(truth, predicted)
        net = ", ".join(f"{row['line']} {row['direction']} {row['predicted'] - row['true']:+d}"
                        for row in errors["lines"] if row["predicted"] != row["true"])
        print(f"seed {seed}: line error {100 * errors['line_error']:.2f} % "
              f"({sum(abs(row['predicted'] - row['true']) for row in errors['lines'])} of "
              f"{sum(row['true'] for row in errors['lines'])}); net {net or 'none'}")
        missed, extra = unmatched(truth, predicted)
        for event in extra:
            times, xy = rows_of(tracks, event.track_id)
            at = xy[np.argmin(np.abs(times - event.timestamp))]
            person = nearest(ground_truth, event.timestamp, at)
            reason = None if person is None else truth_reason(
                ground_truth, person, lines[event.line], event, config)
            print(f"  extra  {event.line} {event.direction} t={event.timestamp:.1f} s "
                  f"x={event.world_xy[0]:.1f}: track {event.track_id} on person {person}: "
                  f"{reason or 'tracks'}")
        for event in missed:
            times, xy = rows_of(ground_truth, event.track_id)
            at = xy[np.argmin(np.abs(times - event.timestamp))]
            track_id = nearest(tracks, event.timestamp, at)
            reason = track_reason(tracks, track_id, event)
            print(f"  missed {event.line} {event.direction} t={event.timestamp:.1f} s "
                  f"x={event.world_xy[0]:.1f}: person {event.track_id}, track {track_id}: "
                  f"{reason or 'tracks'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
