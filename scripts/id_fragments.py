"""Where a scene's extra identities come from: each id born after the first frame, classified.

    python scripts/id_fragments.py crowd [--seed 1] [--option stitch_gap_s=0] [--dataset DIR]
    python scripts/id_fragments.py distorted --localisation
    python scripts/id_fragments.py crowd --switches [--option swap_radius_m=0]

Tracks one case of ``cblrs experiment tracking`` (exact boxes, ``fusion`` defaults unless
``--option`` sets some) and matches its rows to the ground truth frame by frame (Hungarian, 1 m).
Each id born after the first frame is then the *first* id of its person (seen late), the id
taken *after a track ended* (the person's previous id was not reported again: a gap to
stitch), the id taken *after a swap* (the previous id went on with someone else), or *junk*
(never within 1 m of anyone in its first frames). Also printed: how many ground-truth rows no
camera has a box for (occluded in every view), and the lengths of those stretches; with
``--localisation``, the views' ground error by distance from the image centre (do the reference
images undo the lenses' distortion at the edges?).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.tracking import Case, TrackingSetup, build_scene
from cblrs.pipeline import camera_messages, render_scene_references, track_scene


def matches(ground_truth, tracks, radius_m: float = 1.0) -> dict[tuple[int, int], int]:
    """``{(frame, track id): person}`` of the rows within ``radius_m`` (Hungarian per frame)."""
    found = {}
    for frame in np.unique(ground_truth.frame):
        truth, predicted = ground_truth.frame == frame, tracks.frame == frame
        distance = np.linalg.norm(
            ground_truth.world_xy[truth][:, None] - tracks.world_xy[predicted][None], axis=2
        )
        rows, columns = linear_sum_assignment(np.where(distance < radius_m, distance, 1e6))
        for row, column in zip(rows, columns, strict=True):
            if distance[row, column] < radius_m:
                found[(int(frame), int(tracks.track_id[predicted][column]))] = int(
                    ground_truth.track_id[truth][row]
                )
    return found


def classify(ground_truth, tracks) -> tuple[Counter, list[str]]:
    """Count the ids born after the first frame by kind; one line per non-first id."""
    found = matches(ground_truth, tracks)
    person_of = {}  # (frame, person) -> track id
    for (frame, track), person in found.items():
        person_of[(frame, person)] = track
    first = {
        int(t): int(tracks.frame[tracks.track_id == t].min()) for t in np.unique(tracks.track_id)
    }
    last = {
        int(t): int(tracks.frame[tracks.track_id == t].max()) for t in np.unique(tracks.track_id)
    }
    frames = np.unique(ground_truth.frame)
    period = float(np.median(np.diff(np.unique(ground_truth.timestamp))))
    kinds: Counter = Counter()
    lines = []
    for track in sorted(first, key=first.get):
        born = first[track]
        if born == frames[0]:
            kinds["at the first frame"] += 1
            continue
        people = [found[(f, track)] for f in frames[(frames >= born)][:5] if (f, track) in found]
        if not people:
            kinds["junk"] += 1
            continue
        person = max(set(people), key=people.count)
        before = [
            (f, person_of[(f, person)])
            for f in frames[frames < born]
            if person_of.get((f, person), track) != track
        ]
        if not before:
            kinds["first id of its person"] += 1
            continue
        seen, previous = before[-1]
        kind = "after a swap" if last[previous] >= born else "after a track ended"
        kinds[kind] += 1
        lines.append(
            f"  id {track} (person {person}) born frame {born}: {kind}, previous id "
            f"{previous} last on them {(born - seen) * period:.1f} s before"
        )
    return kinds, lines


def unseen(scene) -> tuple[int, int, Counter]:
    """Ground-truth rows without a box in any camera, all rows, and the stretch lengths."""
    boxes: Counter = Counter()
    for index, frame in enumerate(scene.frames):
        for detections in scene.detections[index]:
            boxes.update((int(frame), int(person)) for person in detections.object_id)
    truth = scene.ground_truth
    stretches: Counter = Counter()
    missing = 0
    for person in np.unique(truth.track_id):
        run = 0
        for frame in np.sort(truth.frame[truth.track_id == person]):
            if boxes[(int(frame), int(person))] == 0:
                run += 1
                missing += 1
            elif run:
                stretches[run] += 1
                run = 0
        if run:
            stretches[run] += 1
    return missing, len(truth.frame), stretches


def switches(scene, tracks, minimum: int = 5) -> list[tuple[int, int, int, int, float, bool]]:
    """Each time a track goes on with another person for ``minimum`` matched frames or more:
    (track, person before, person after, frame, closest the two people came in the 20 frames
    before and 2 after, whether either had no box in any camera for a frame or more from 8
    frames before to 2 after)."""
    found = matches(scene.ground_truth, tracks)
    truth = scene.ground_truth
    where = {
        (int(f), int(t)): xy
        for f, t, xy in zip(truth.frame, truth.track_id, truth.world_xy, strict=True)
    }
    boxes: Counter = Counter()
    for index, frame in enumerate(scene.frames):
        for detections in scene.detections[index]:
            boxes.update((int(frame), int(person)) for person in detections.object_id)
    sequence: dict[int, list[tuple[int, int]]] = {}
    for (frame, track), person in sorted(found.items()):
        sequence.setdefault(track, []).append((frame, person))
    events = []
    for track, rows in sorted(sequence.items()):
        runs: list[list[int]] = []  # [person, first, last, frames]
        for frame, person in rows:
            if runs and runs[-1][0] == person:
                runs[-1][2], runs[-1][3] = frame, runs[-1][3] + 1
            else:
                runs.append([person, frame, frame, 1])
        kept: list[list[int]] = []
        for run in (run for run in runs if run[3] >= minimum):
            if kept and kept[-1][0] == run[0]:
                kept[-1][2] = run[2]
            else:
                kept.append(list(run))
        for before, after in itertools.pairwise(kept):
            a, b, last, first = before[0], after[0], before[2], after[1]
            gaps = [
                float(np.linalg.norm(where[(f, a)] - where[(f, b)]))
                for f in range(last - 20, first + 3)
                if (f, a) in where and (f, b) in where
            ]
            hidden = any(
                boxes[(f, person)] == 0 for f in range(last - 8, first + 3) for person in (a, b)
            )
            events.append((track, a, b, first, min(gaps, default=float("nan")), hidden))
    return events


def localisation(scene, references) -> list[tuple[str, int, float, int, float]]:
    """Ground error of the located views (box bottom-centre looked up in the camera's
    reference image) against the ground truth, by distance of the foot pixel from the image
    centre: (band, views, median metres, views more than 1 m off, largest metres). Bands are
    quarters of the half-diagonal. The median alone hides a few views far off (a lens model
    folding back past its field, see ``Camera.field_radius``)."""
    truth = scene.ground_truth
    where = {
        (int(f), int(t)): xy
        for f, t, xy in zip(truth.frame, truth.track_id, truth.world_xy, strict=True)
    }
    errors: list[list[float]] = [[], [], [], []]
    for message in camera_messages(scene, references):
        camera = scene.camera_names.index(message.camera_id)
        detections = scene.detections[int(np.flatnonzero(scene.frames == message.frame)[0])][camera]
        world_xy, valid, _ = references[camera].planes.decode(message.colour)
        width, height = scene.cameras[camera].image_size
        foot = np.column_stack(
            [(detections.xyxy[:, 0] + detections.xyxy[:, 2]) / 2, detections.xyxy[:, 3]]
        )
        radius = np.hypot(foot[:, 0] - width / 2, foot[:, 1] - height / 2) / np.hypot(
            width / 2, height / 2
        )
        for index in np.flatnonzero(valid):
            true_xy = where.get((int(message.frame), int(detections.object_id[index])))
            if true_xy is not None:
                band = min(int(radius[index] * 4), 3)
                errors[band].append(float(np.linalg.norm(world_xy[index] - true_xy)))
    names = ("0-25 %", "25-50 %", "50-75 %", "75-100 %")
    return [
        (name, len(values), float(np.median(values)) if values else float("nan"),
         int(np.sum(np.asarray(values) > 1.0)), max(values, default=float("nan")))
        for name, values in zip(names, errors, strict=True)
    ]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", choices=("crowd", "distorted", "roundabout", "crossroads"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--size", type=int, default=0, help="people or cars (0: default)")
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        help="a fusion option NAME=JSON, e.g. stitch_gap_s=0",
    )
    parser.add_argument("--dataset", type=Path, default=None, help="WILDTRACK (crowd)")
    parser.add_argument(
        "--switches",
        action="store_true",
        help="also each time a track goes on with another person (for 5 frames or more)",
    )
    parser.add_argument(
        "--localisation",
        action="store_true",
        help="also the views' ground error by distance from the image centre",
    )
    args = parser.parse_args(argv)
    options = {}
    for text in args.option:
        name, _, value = text.partition("=")
        try:
            options[name] = json.loads(value)
        except json.JSONDecodeError:
            print(
                f"--option {text!r}: the value must be JSON (a number, true, ...).", file=sys.stderr
            )
            return 2
    case = Case(args.scene, args.seed, args.size)
    scene = build_scene(case, TrackingSetup(wildtrack=args.dataset))
    references = render_scene_references(scene)
    tracks = track_scene(scene, references=references, **options).tracks
    metrics = evaluate(scene.ground_truth, tracks)
    people = len(np.unique(scene.ground_truth.track_id))
    print(
        f"{case.scene_label}, exact boxes{', ' if options else ''}"
        f"{', '.join(f'{k}={v}' for k, v in options.items())}: HOTA {metrics.HOTA:.1f}, "
        f"AssA {metrics.AssA:.1f}, DetA {metrics.DetA:.1f}, "
        f"ids {len(np.unique(tracks.track_id))} / {people}"
    )
    kinds, lines = classify(scene.ground_truth, tracks)
    print(
        "ids by when and why they were born: "
        + ", ".join(f"{kind} {count}" for kind, count in kinds.most_common())
    )
    print("\n".join(lines))
    missing, rows, stretches = unseen(scene)
    print(
        f"ground-truth rows no camera has a box for: {missing} of {rows} "
        f"({100 * missing / rows:.1f} %); stretches (frames: count): "
        + ", ".join(f"{length}: {count}" for length, count in sorted(stretches.items()))
    )
    if args.switches:
        events = switches(scene, tracks)
        for track, a, b, frame, closest, hidden in events:
            print(
                f"  track {track}: person {a} -> {b} at frame {frame}, closest {closest:.2f} m"
                + (", one of them unseen by every camera around it" if hidden else "")
            )
        gaps = [event[4] for event in events]
        print(
            f"tracks going on with another person: {len(events)}"
            + (
                f", the two {min(gaps):.2f}-{max(gaps):.2f} m apart at closest (median "
                f"{float(np.median(gaps)):.2f}), {sum(event[5] for event in events)} with one "
                "unseen by every camera around it"
                if events
                else ""
            )
        )
    if args.localisation:
        print(
            "views' ground error by the foot pixel's distance from the image centre "
            "(share of the half-diagonal): "
            + ", ".join(
                f"{band} {error:.2f} m ({views} views, {far} more than 1 m off, largest "
                f"{largest:.1f} m)"
                for band, views, error, far, largest in localisation(scene, references)
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
