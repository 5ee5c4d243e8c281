"""``cblrs track``: track a WILDTRACK or MultiviewX folder through the colour reference images."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from cblrs.cli.clock_options import (
    add_clock_options,
    clock_simulation,
    is_synthetic,
    synthetic_scene,
)
from cblrs.cli.common import (
    UsageError,
    add_dataset_argument,
    add_output_options,
    parse_frame_range,
    print_json,
)
from cblrs.cli.detector_options import (
    DETECTIONS_HELP,
    add_detector_options,
    detection_source,
    drop_hidden_feet,
    real_detections,
)
from cblrs.datasets import load_scene, simulate_detections, write_tracks
from cblrs.detections import SURE_CONFIDENCE
from cblrs.matching import DEFAULT_MATCHER, MATCHERS
from cblrs.pipeline import camera_positions, scene_planes, scene_references, track_scene
from cblrs.plane import PlaneSet


def register(subparsers) -> None:
    """Add the ``cblrs track`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "track",
        help="track a multi-camera dataset and write world tracks (AI City format)",
        description=(
            "Render each camera's colour reference image, turn every box into a camera message "
            "(target pixel -> colour), match the messages into global tracks and write them "
            "in the AI City 2024 text format (world metres, one row per frame and track). "
            "Detections are the dataset's annotated boxes, optionally degraded by a simulated "
            "detector (--drop, --jitter, --false-positives); or a real detector run on the "
            "dataset's images (--detector onnx --model M.onnx, images in Image_subsets/C<k>/); "
            "or your own detector's boxes (--detections DIR). Cameras can be given their own "
            "clocks, frame rates and lost messages (--clock-offset-ms, --clock-jitter-ms, "
            "--camera-fps, --drop-messages, --clock-error)."
        ),
    )
    add_dataset_argument(
        parser, "WILDTRACK or MultiviewX folder, or synthetic:PRESET (plaza, roundabout)",
        required=True, positional_alias=True,
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="TRACKS.txt",
        help="output tracks file (overwritten)",
    )
    parser.add_argument(
        "--matcher",
        choices=sorted(MATCHERS),
        default=DEFAULT_MATCHER,
        help=f"matcher (default: {DEFAULT_MATCHER})",
    )
    parser.add_argument(
        "--frames", metavar="FIRST:LAST", help="only these native frame numbers (inclusive)"
    )
    parser.add_argument(
        "--drop",
        type=float,
        default=0.0,
        metavar="P",
        help="probability a box is missed (default 0)",
    )
    parser.add_argument(
        "--jitter",
        type=float,
        default=0.0,
        metavar="F",
        help="box edge noise as a fraction of the box size (default 0)",
    )
    parser.add_argument(
        "--false-positives",
        type=float,
        default=0.0,
        metavar="N",
        help="mean spurious boxes per frame and camera (default 0)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="S",
        help="seed of the simulated detector (default 0)",
    )
    parser.add_argument(
        "--bits",
        type=int,
        choices=(8, 16),
        default=None,
        help="bits per colour channel of the reference images (default 16, or the site's)",
    )
    parser.add_argument(
        "--site",
        type=Path,
        help="a site file giving the cameras' geometry, positions and planes instead of the "
        "dataset's calibration (e.g. a calibration from clicked points)",
    )
    parser.add_argument(
        "--key",
        type=Path,
        help="pseudo coordinates (docs/privacy.md): render the references with this key file, "
        "so the matcher sees and writes pseudo coordinates only (--score maps them back)",
    )
    parser.add_argument(
        "--score", action="store_true",
        help="also score the tracks against the scene's ground truth (as cblrs eval, at the "
        "frames of which some camera's message arrived)",
    )
    add_detector_options(parser, detections_help=DETECTIONS_HELP)
    parser.add_argument(
        "--high-confidence", type=float, metavar="S",
        help="fusion: detections scored below S are low-confidence, kept only where a track "
        "seen by two cameras or another camera's sure view confirms them (default "
        f"{SURE_CONFIDENCE}; 0: every detection is sure)",
    )
    add_clock_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs track`` with its parsed arguments; the exit code."""
    _reuse_freed_memory()
    for name in ("drop", "jitter", "false_positives"):
        value = getattr(args, name)
        if not value >= 0:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 0, got {value}.")
    if args.drop > 1:
        raise UsageError(f"--drop is a probability and must be at most 1, got {args.drop}.")
    if args.high_confidence is not None and (
        args.matcher != "fusion" or not 0.0 <= args.high_confidence <= 1.0
    ):
        raise UsageError(
            "--high-confidence is a score within 0..1 for --matcher fusion, "
            f"got {args.high_confidence}."
        )
    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give a file name.")
    source = detection_source(args)
    simulated = bool(args.drop or args.jitter or args.false_positives)
    if simulated and source != "annotations":
        raise UsageError(
            "--drop, --jitter and --false-positives simulate a detector on the annotated "
            "boxes; leave them out with --detector or --detections."
        )
    clocks = clock_simulation(args)
    frame_range = parse_frame_range(args.frames) if args.frames else None
    if is_synthetic(args.dataset):
        if args.site is not None or source != "annotations":
            raise UsageError(
                "a synthetic scene has no images, detection files or site: leave out "
                "--site, --detector and --detections."
            )
        scene = synthetic_scene(args.dataset, clocks, args.duration)
    else:
        scene = load_scene(args.dataset)
    if frame_range is not None:
        scene = scene.select_frames(*frame_range)
    options: dict = {}
    if args.high_confidence is not None:
        options["high_confidence"] = args.high_confidence
    started = time.perf_counter()
    key = _load_key(args)
    if key is not None:
        # lazy: pseudo coordinates only with --key (tracking without it need not load them)
        from cblrs.privacy.frame import (
            positions_to_pseudo,
            render_pseudo_reference,
            tracks_to_site,
        )
    if args.site is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.site import load_site

        site = load_site(args.site)
        if site.pseudo_key_id is not None:
            raise UsageError(
                f"{args.site} is a pseudo site; track with the real site and --key instead."
            )
        scene = site.scene(scene)
        if key is None:
            references = [site.render_reference(name, args.bits) for name in scene.camera_names]
        else:
            site_planes = site.require_planes("track")
            planes = PlaneSet([replace(plane, bits=args.bits or site_planes.bits)
                               for plane in site_planes])
            references = [render_pseudo_reference(site.camera(name).camera, planes, key)
                          for name in scene.camera_names]
        if args.matcher == "fusion":
            positions = site.camera_positions()
            options["camera_positions"] = {
                name: positions[name] for name in scene.camera_names if name in positions
            }
    elif key is None:
        references = scene_references(scene, args.bits or 16)
    else:
        references = [render_pseudo_reference(camera, scene_planes(scene, args.bits or 16), key)
                      for camera in scene.cameras]
        if args.matcher == "fusion":
            options["camera_positions"] = camera_positions(scene)
    if key is not None and "camera_positions" in options:
        # The matcher works in the pseudo frame: its cameras are where the key puts them.
        options["camera_positions"] = positions_to_pseudo(options["camera_positions"], key)
    render_seconds = time.perf_counter() - started
    scene, detector_summary = real_detections(args, scene, references, source, args.quiet)
    if simulated:
        scene = simulate_detections(
            scene,
            drop=args.drop,
            jitter=args.jitter,
            false_positives=args.false_positives,
            seed=args.seed,
        )
    result = track_scene(
        scene, args.matcher, references=references, progress=not args.quiet,
        drop_hidden_feet=drop_hidden_feet(args, source), clocks=clocks, **options,
    )
    # The sidecar keeps the classes and frame rate that the AI City format cannot hold.
    write_tracks(args.out, result.tracks, frames_per_second=scene.frames_per_second)
    tracks = result.tracks
    summary = {
        "dataset": str(args.dataset),
        "matcher": args.matcher,
        "frames": len(scene.frames),
        "cameras": len(scene.cameras),
        "messages": result.message_count,
        "detections": result.detection_count,
        "tracks": len(set(tracks.track_id.tolist())),
        "rows": len(tracks),
        "matcher_seconds": round(result.matcher_seconds, 4),
        "render_seconds": round(render_seconds, 4),
        "total_seconds": round(time.perf_counter() - started, 4),
        "out": str(args.out),
        "source": source,
    }
    if detector_summary is not None:
        summary["detector"] = detector_summary
    if clocks is not None:
        summary["captured_frames"] = len(result.captured_frames)
    if result.clocks is not None:
        summary["clocks"] = result.clocks
    if key is not None:
        summary["pseudo_key_id"] = key.key_id
    if args.score:
        scored = result if key is None else replace(
            result, tracks=tracks_to_site(result.tracks, key))
        summary["scores"] = _score(args.dataset, scene, scored)
    if args.json:
        print_json(summary)
    else:
        print(
            f"{summary['matcher']}: {summary['frames']} frames x {summary['cameras']} cameras, "
            f"{summary['detections']} detections -> {summary['tracks']} tracks, "
            f"{summary['rows']} rows in {summary['out']} (matcher {result.matcher_seconds:.2f} s, "
            f"total {summary['total_seconds']:.2f} s incl. rendering {render_seconds:.2f} s)"
        )
        if detector_summary is not None and "model" in detector_summary:
            print(
                f"detector {detector_summary['model']} ({detector_summary['tiling']} tiling): "
                f"{detector_summary['detector_ms_per_image']:.1f} ms per image, "
                f"{detector_summary['images']} images"
                + ("; skipped (unusable image file): " + ", ".join(
                    f"{count} {reason}" for reason, count in
                    sorted(detector_summary["images_skipped"].items()))
                   if detector_summary.get("images_skipped") else "")
            )
        for name, report in (result.clocks or {}).items():
            if report["beyond_tolerance"] or report["coarse_corrections"]:
                print(f"camera {name}: clock off by {report['offset_s']:+.3f} s against the "
                      "other cameras (estimated from the tracks; its timestamps were corrected)")
        if args.score:
            scores = summary["scores"]
            print("  ".join(f"{key} {scores[key]:.2f}"
                            for key in ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")))
    return 0


def _reuse_freed_memory() -> None:
    """Let glibc's malloc keep the blocks numpy frees for the next ones.

    By default a block of 128 KiB or more (a reference image's sampled pixels, 1 MiB a
    column; a crowded window's pair arrays) is mapped from the system when allocated and
    unmapped when freed, and the heap's free top is given back past 128 KiB: every such
    temporary costs its pages' first-touch faults again, half of the 33,000 page faults of
    tracking WILDTRACK. Blocks below 32 MiB then come from the heap and up to 64 MiB of it
    stays free for reuse, for the few seconds this command runs. Elsewhere than glibc
    (no ``mallopt``) nothing changes.
    """
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD
    mallopt(-1, 64 << 20)  # M_TRIM_THRESHOLD


def _load_key(args: argparse.Namespace):
    """The ``--key`` file's key, or None."""
    if args.key is None:
        return None
    # lazy: pseudo coordinates only with --key (tracking without it need not load them)
    from cblrs.privacy.key import PseudoKey

    return PseudoKey.load(args.key)


def _score(dataset: Path, scene, result) -> dict:
    """The tracks' scores at the frames some camera captured (the annotated-area rule of
    ``cblrs eval`` for data set folders)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.calibration import default_ground
    from cblrs.evaluation import evaluate

    area = None if is_synthetic(dataset) else default_ground(dataset)
    metrics = evaluate(scene.ground_truth, result.tracks, frames=result.captured_frames,
                       area=area)
    return {key: round(value, 4) for key, value in metrics.to_dict().items()
            if isinstance(value, float)}
