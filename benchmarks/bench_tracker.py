"""Throughput of the fusion tracker (and the paper matcher) on one core.

Synthetic load: detections per second at 50/100/200/400 live tracks and 1/4/8 cameras
(messages pre-built, only ``matcher.update`` timed, medians over repeats). WILDTRACK: the
whole sequence end to end, with the reference images already rendered ("render excluded")
and with rendering ("render included"); loading the annotation files is reported apart.

    python benchmarks/bench_tracker.py [--json] [--repeats 5] [--frames 60]
        [--tracks 50,100,200,400] [--cameras 1,4,8] [--matcher fusion] [--dataset DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from cblrs.matching.benchmark import measure_dataset, measure_throughput

REPO_ROOT = Path(__file__).resolve().parents[1]


def _numbers(text: str) -> list[int]:
    return [int(part) for part in text.split(",") if part.strip()]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=60, help="timed frames per run")
    parser.add_argument("--tracks", type=_numbers, default=[50, 100, 200, 400])
    parser.add_argument("--cameras", type=_numbers, default=[1, 4, 8])
    parser.add_argument("--matcher", default="fusion")
    parser.add_argument(
        "--dataset", type=Path,
        default=Path(os.environ.get("CBLRS_WILDTRACK", REPO_ROOT.parent / "shared/data/wildtrack")),
        help="WILDTRACK folder for the end-to-end run (skipped if missing)",
    )
    args = parser.parse_args(argv)

    synthetic = [
        measure_throughput(tracks, cameras, frames=args.frames, matcher=args.matcher,
                           repeats=args.repeats)
        for tracks in args.tracks
        for cameras in args.cameras
    ]
    dataset = None
    if (args.dataset / "calibrations").is_dir():
        dataset = measure_dataset(args.dataset, matcher=args.matcher, repeats=args.repeats)

    if args.json:
        print(json.dumps({"synthetic": synthetic, "dataset": dataset}, indent=2))
        return 0
    print(f"{args.matcher}: detections/s on one core (median of {args.repeats}; "
          f"{args.frames} timed frames at 10 fps)")
    header = "tracks  " + "  ".join(f"{cameras:>2d} cam: det/s   ms/frame"
                                    for cameras in args.cameras)
    print(header)
    for tracks in args.tracks:
        cells = []
        for cameras in args.cameras:
            row = next(r for r in synthetic if r["live_tracks"] == tracks
                       and r["cameras"] == cameras)
            rate, milliseconds = row["detections_per_second"], row["milliseconds_per_frame"]
            cells.append(f"{rate:>14,.0f} {milliseconds:>9.2f}")
        print(f"{tracks:>6d}  " + "  ".join(cells))
    if dataset:
        print(
            f"\n{dataset['dataset']}: {dataset['frames']} frames x {dataset['cameras']} cameras, "
            f"{dataset['detections']} detections\n"
            f"  tracking, render excluded: {dataset['track_seconds']:.3f} s "
            f"(matcher alone {dataset['matcher_seconds']:.3f} s)\n"
            f"  tracking, render included: {dataset['total_seconds']:.3f} s "
            f"(rendering {dataset['render_seconds']:.3f} s)\n"
            f"  loading the annotations (not included): {dataset['load_seconds']:.3f} s"
        )
    else:
        print(f"\n(no dataset at {args.dataset}; end-to-end run skipped)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
