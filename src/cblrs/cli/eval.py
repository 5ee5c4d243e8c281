"""``cblrs eval``: score AI City format tracks against a dataset's ground truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cblrs.calibration import default_ground
from cblrs.cli.common import (
    UsageError,
    add_dataset_argument,
    add_output_options,
    format_table,
    parse_frame_range,
    print_json,
)
from cblrs.datasets.aicity import read_tracks
from cblrs.datasets.multiview import load_scene
from cblrs.detections import Tracks
from cblrs.errors import DatasetError
from cblrs.evaluation import Metrics, evaluate
from cblrs.evaluation.checks import check_predictions


def register(subparsers) -> None:
    """Add the ``cblrs eval`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "eval",
        help="HOTA, DetA, AssA, LocA, MOTA, IDF1 of tracks against ground truth",
        description=(
            "Score world tracks (AI City 2024 text format) against the ground truth of a "
            "WILDTRACK or MultiviewX folder, or of an AI City format ground-truth file, under "
            "the AI City 2024 protocol: one sequence for all cameras, the first row per "
            "(frame, id) counts, similarity max(0, 1 - d / 2 m) for HOTA, MOTA and IDF1 "
            "within 1 m. Scores are percentages."
        ),
    )
    add_dataset_argument(
        parser, "WILDTRACK or MultiviewX folder, or an AI City format ground-truth .txt",
        required=True, positional_alias=True,
    )
    parser.add_argument("tracks", type=Path, metavar="TRACKS.txt", help="predicted tracks")
    parser.add_argument(
        "--frames",
        metavar="FIRST:LAST",
        help="only these native frame numbers (inclusive; either side may be empty)",
    )
    parser.add_argument(
        "--site",
        type=Path,
        help="score only inside the site file's planes (what its cameras can locate)",
    )
    parser.add_argument(
        "--key",
        type=Path,
        help="the tracks are in pseudo coordinates (cblrs track --key, a pseudo-site matcher): "
        "map them back to the site with this key file before scoring",
    )
    parser.add_argument(
        "--whole-plane",
        action="store_true",
        help="WILDTRACK / MultiviewX: also score predictions outside the annotated area that "
        "match no ground truth (by default they are not scored: the data sets annotate only "
        "people inside that area)",
    )
    add_output_options(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs eval`` with its parsed arguments; the exit code."""
    first, last = parse_frame_range(args.frames) if args.frames else (None, None)
    ground_truth = read_ground_truth(args.dataset)
    predictions = read_tracks(args.tracks)
    if args.key is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.privacy import PseudoKey, tracks_to_site

        predictions = tracks_to_site(predictions, PseudoKey.load(args.key))
    frames = select_frames(ground_truth, first, last, args.frames)
    note = ""
    if args.site is not None:
        ground_truth, predictions, note = inside_site(args.site, ground_truth, predictions)
    # Scored anyway, but a file that looks wrong is said to look wrong.
    for warning in check_predictions(ground_truth, predictions, frames):
        print(f"cblrs eval: warning: {warning}", file=sys.stderr)
    area = None if args.whole_plane or not args.dataset.is_dir() else default_ground(args.dataset)
    metrics = evaluate(ground_truth, predictions, frames=frames, area=area)
    if args.json:
        print_json(metrics.to_dict())
    else:
        print(format_summary(metrics))
        if note:
            print(note)
    return 0


def inside_site(site_path: Path, ground_truth: Tracks, predictions: Tracks):
    """Ground truth and predictions restricted to the site's planes, and a sentence saying so."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.site import load_site

    site = load_site(site_path)
    if site.pseudo_key_id is not None:
        raise UsageError(
            f"{site_path} is a pseudo site; score inside the real site's planes (--site SITE, "
            "with --key for pseudo tracks)."
        )
    planes = site.require_planes("eval --site")

    def inside(tracks: Tracks) -> np.ndarray:
        keep = np.zeros(len(tracks), dtype=bool)
        for plane in planes:
            keep |= plane.contains(tracks.world_xy)
        return keep

    truth_kept, predicted_kept = inside(ground_truth), inside(predictions)
    note = (
        f"scored inside {site_path.name}'s planes: {int(truth_kept.sum())} of "
        f"{len(ground_truth)} ground-truth rows, {int(predicted_kept.sum())} of "
        f"{len(predictions)} predicted rows"
    )
    return ground_truth[truth_kept], predictions[predicted_kept], note


def read_ground_truth(path: Path) -> Tracks:
    """Ground truth from a WILDTRACK/MultiviewX folder or an AI City format file."""
    if path.is_dir():
        return load_scene(path).ground_truth
    if path.is_file():
        return read_tracks(path)
    raise DatasetError(f"{path} is neither a dataset folder nor a ground-truth file.")


def select_frames(
    ground_truth: Tracks, first: int | None, last: int | None, text: str | None
) -> np.ndarray | None:
    """Ground-truth frame numbers in [first, last], or None for all of them."""
    if first is None and last is None:
        return None
    frames = np.unique(ground_truth.frame)
    keep = np.ones(len(frames), dtype=bool)
    if first is not None:
        keep &= frames >= first
    if last is not None:
        keep &= frames <= last
    if not keep.any():
        span = f"{frames.min()}..{frames.max()}" if len(frames) else "none"
        raise UsageError(f"--frames {text} holds no ground-truth frame (ground truth: {span}).")
    return frames[keep]


def format_summary(metrics: Metrics) -> str:
    """The scores as a table, with the frame and id counts they were computed on."""
    scores = metrics.to_dict()
    table = format_table(list(scores), [list(scores.values())])
    return (
        f"{table}\n"
        f"(percent; {metrics.num_timesteps} frames, {metrics.num_gt_ids} ground-truth ids, "
        f"{metrics.num_predicted_ids} predicted ids, {metrics.IDSW} id switches)"
    )
