"""``cblrs experiment``: the paper's experiments rerun — targeting (IV-B), resolution, clicked
calibration — the count accuracy of the analytics (counts), identity where it is hard
(tracking), what pseudo coordinates do not hide (pseudo) and identities across the planes of
a city (planes).

Each prints a markdown table (or ``--json``); ``--out DIR`` also writes
``DIR/experiment_<name>.json``, ``.md`` and the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

from cblrs.cli.common import (
    InputError,
    UsageError,
    add_dataset_argument,
    add_output_options,
    print_json,
)


def register(subparsers) -> None:
    """Add the ``cblrs experiment`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "experiment",
        help="rerun the paper's experiments: targeting (IV-B), resolution; clicked "
        "calibration; count accuracy; pseudo-coordinate recovery; identities across planes",
        description="Rerun the paper's experiments on the synthetic world and WILDTRACK.",
    )
    kinds = parser.add_subparsers(dest="experiment", metavar="EXPERIMENT")

    targeting = kinds.add_parser(
        "targeting",
        help="AOD per camera tilt x VTP x yaw, and geometry-aware targeting",
    )
    targeting.add_argument(
        "--tilts", default="10,20,30,40,50,60,70,80,90", help="camera tilts, degrees"
    )
    targeting.add_argument("--yaws", default="0,45,90", help="object yaws, degrees")
    targeting.add_argument("--draws", type=int, default=4, help="noisy draws per position")
    targeting.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_dataset_argument(
        targeting, "WILDTRACK folder for the annotated-box check (default: $CBLRS_WILDTRACK or "
        "../shared/data/wildtrack)", option_aliases=("--wildtrack",),
    )
    targeting.add_argument(
        "--no-wildtrack", action="store_true", help="skip the WILDTRACK annotated-box check"
    )
    targeting.add_argument(
        "--tracking",
        default="",
        help="also track these scenes with box and geometric targeting and score them "
        "(comma-separated: wildtrack, plaza, roundabout)",
    )
    targeting.add_argument("--out", type=Path, help="write JSON, markdown and heat maps here")
    targeting.add_argument("--figures", type=Path, help="write the PNGs here (default: --out)")
    add_output_options(targeting)
    targeting.set_defaults(handler=run, experiment="targeting")

    resolution = kinds.add_parser(
        "resolution", help="plane size x bits -> raster step, and its effect on LocA / HOTA"
    )
    resolution.add_argument(
        "--sizes",
        default="50,100,200,500",
        help="square plane sides in metres (besides the scene plane)",
    )
    resolution.add_argument("--bits", default="8,16", help="bit depths")
    resolution.add_argument(
        "--frames", type=int, default=None, help="use only the first N frames of each scene"
    )
    resolution.add_argument(
        "--scenes", default="wildtrack,plaza", help="scenes: wildtrack and/or plaza (synthetic)"
    )
    add_dataset_argument(
        resolution, "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack)",
        option_aliases=("--wildtrack",),
    )
    resolution.add_argument("--out", type=Path, help="write JSON, markdown and the plot here")
    resolution.add_argument("--figures", type=Path, help="write the PNG here (default: --out)")
    add_output_options(resolution)
    resolution.set_defaults(handler=run, experiment="resolution")

    calibration = kinds.add_parser(
        "calibration",
        help="clicked calibrations (N points per camera) vs the lab calibration on WILDTRACK",
    )
    calibration.add_argument(
        "--counts", default="4,6,10,20", help="correspondences per camera (default 4,6,10,20)"
    )
    calibration.add_argument("--seeds", default="0,1,2,3,4", help="one run per seed")
    calibration.add_argument(
        "--noise-px", type=float, default=2.0, help="click noise, pixels (default 2)"
    )
    calibration.add_argument(
        "--point-frames", type=int, default=5, help="frames the points come from (default 5)"
    )
    calibration.add_argument(
        "--click-px",
        type=float,
        default=2.0,
        help="click noise the site states, pixels (cblrs calibrate's default, 2)",
    )
    calibration.add_argument(
        "--ground-m",
        type=float,
        default=0.1,
        help="ground accuracy the site states, metres (cblrs calibrate's default, 0.1)",
    )
    add_dataset_argument(
        calibration, "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack)",
        option_aliases=("--wildtrack",),
    )
    calibration.add_argument("--out", type=Path, help="write JSON and markdown here")
    calibration.add_argument(
        "--figures", type=Path, help="write a picture of one clicked calibration here"
    )
    add_output_options(calibration)
    calibration.set_defaults(handler=run, experiment="calibration")
    counts = kinds.add_parser(
        "counts",
        help="analytics on tracks vs on ground truth: line, zone, dwell and OD count errors",
    )
    counts.add_argument("--scenes", default="wildtrack,plaza,roundabout,roundabout-traffic",
                        help="scenes (comma-separated)")
    counts.add_argument("--matchers", default="fusion,paper", help="matchers (comma-separated)")
    counts.add_argument("--seeds", default="1,2,3", help="simulated-detector seeds")
    counts.add_argument("--drop", type=float, default=0.2, help="simulated detector drop (0.2)")
    counts.add_argument("--jitter", type=float, default=0.05, help="box edge jitter (0.05)")
    counts.add_argument("--sites", type=Path, default=None,
                        help="folder of <scene>.yaml site files (default: the repository's sites/)")
    add_dataset_argument(
        counts, "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack)",
        option_aliases=("--wildtrack",),
    )
    counts.add_argument("--out", type=Path, help="write JSON, markdown and figures here")
    counts.add_argument("--figures", type=Path, help="write the PNGs here (default: --out)")
    add_output_options(counts)
    counts.set_defaults(handler=run, experiment="counts")
    tracking = kinds.add_parser(
        "tracking",
        help="identity where it is hard: traffic, crowds, distortion, detectors (issue 19)",
        description="Track issue 19's cases (scenes x seeds x kinds of boxes) with fusion's "
        "defaults and print one table: HOTA, AssA, IDF1, MOTA, ids, line and OD errors; "
        "held-out checks last.",
    )
    tracking.add_argument(
        "--scenes", default="", help="only these scenes (comma-separated: roundabout, "
        "crossroads, crowd, distorted, wildtrack, multiviewx; default all)",
    )
    tracking.add_argument("--no-held-out", action="store_true",
                          help="skip the held-out checks")
    tracking.add_argument("--without-rules", action="store_true",
                          help="the tracker without issue 19's rules (tracks leaving the plane "
                          "end, vehicles cannot turn on the spot, multi-view confirmation, "
                          "stitching), for comparison")
    tracking.add_argument("--sites", type=Path, default=None,
                          help="folder of <scene>.yaml site files (default: the repository's "
                          "sites/)")
    add_dataset_argument(
        tracking, "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack)",
        option_aliases=("--wildtrack",),
    )
    tracking.add_argument("--multiviewx", type=Path, default=None,
                          help="MultiviewX folder (default ../shared/data/multiviewx)")
    tracking.add_argument("--model", type=Path, default=None,
                          help="ONNX detector (default ../shared/models/yolox_nano.onnx)")
    tracking.add_argument("--jobs", type=int, default=None,
                          help="scenes tracked at once, one process each (default: the "
                               "machine's cores; the rows do not depend on it)")
    tracking.add_argument("--out", type=Path, help="write JSON and markdown here")
    add_output_options(tracking)
    tracking.set_defaults(handler=run, experiment="tracking")

    pseudo = kinds.add_parser(
        "pseudo",
        help="what pseudo coordinates do not hide: recovering the key's transform from the "
        "database with landmarks, camera masts or a map of where people walk",
    )
    pseudo.add_argument("--landmarks", default="2,3,5,10", help="numbers of landmarks k")
    pseudo.add_argument("--sigmas", default="0.1,0.5,2",
                        help="landmark position errors per axis, metres")
    pseudo.add_argument("--mast-sigmas", default="0.5,2",
                        help="errors of the adversary's camera-mast positions, metres")
    pseudo.add_argument("--draws", type=int, default=200, help="draws per landmark row")
    pseudo.add_argument("--keys", type=int, default=5, help="keys per walkway row")
    pseudo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_dataset_argument(
        pseudo, "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack)",
    )
    pseudo.add_argument("--out", type=Path, help="write JSON and markdown here")
    add_output_options(pseudo)
    pseudo.set_defaults(handler=run, experiment="pseudo")

    planes = kinds.add_parser(
        "planes",
        help="identities and origin-destination across the planes of a synthetic street "
        "(4 planes, 16 cameras): single plane vs unlinked vs linked",
    )
    planes.add_argument("--seed", type=int, default=0, help="the world's seed (default 0)")
    planes.add_argument("--seeds", default="1,2,3", help="simulated-detector seeds")
    planes.add_argument("--drop", type=float, default=0.2, help="simulated detector drop (0.2)")
    planes.add_argument("--jitter", type=float, default=0.05, help="box edge jitter (0.05)")
    planes.add_argument("--people", type=int, default=40, help="people with a trip (40)")
    planes.add_argument("--cars", type=int, default=12, help="cars (12)")
    planes.add_argument("--spawn", type=float, default=40.0, metavar="SECONDS",
                        help="trips start within this many seconds (40)")
    planes.add_argument("--max-trip", type=float, default=110.0, metavar="METRES",
                        help="no trip is longer (110)")
    planes.add_argument("--fps", type=float, default=10.0, help="frame rate of the world (10)")
    planes.add_argument("--out", type=Path, help="write JSON and markdown here")
    add_output_options(planes)
    planes.set_defaults(handler=run, experiment="planes")

    def usage(args: argparse.Namespace) -> int:
        parser.print_help()
        return 2

    parser.set_defaults(handler=usage)


def parse_numbers(text: str, option: str) -> tuple[float, ...]:
    """``"10,20,30"`` -> (10.0, 20.0, 30.0); a clear error otherwise."""
    try:
        values = tuple(float(value) for value in text.split(",") if value.strip())
    except ValueError:
        raise UsageError(f"{option} {text!r} must be comma-separated numbers.") from None
    if not values:
        raise UsageError(f"{option} needs at least one number.")
    # Whole numbers stay integers so that they print (and key JSON tables) as "30", not "30.0".
    return tuple(int(value) if value.is_integer() else value for value in values)


def _write(out: Path, name: str, result: dict[str, Any], text: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / f"experiment_{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / f"experiment_{name}.md").write_text(text + "\n")


def run_targeting_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment targeting``: (result, markdown)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.bench.cameras import find_wildtrack
    from cblrs.experiments.targeting import (
        TargetingSetup,
        plot_targeting,
        run_targeting,
        targeting_report,
    )
    from cblrs.experiments.targeting_scenes import wildtrack_targeting

    tilts = parse_numbers(args.tilts, "--tilts")
    if not all(0 < tilt <= 90 for tilt in tilts):
        raise UsageError(f"--tilts must lie in (0, 90] degrees, got {args.tilts!r}.")
    if args.draws <= 0:
        raise UsageError(f"--draws must be a positive integer, got {args.draws}.")
    tracking_scenes = [name.strip() for name in args.tracking.split(",") if name.strip()]
    unknown = [name for name in tracking_scenes if name not in ("wildtrack", "plaza", "roundabout")]
    if unknown:
        raise UsageError(
            f"--tracking scenes must be wildtrack, plaza or roundabout; got {unknown}."
        )
    setup = TargetingSetup(
        tilts_deg=tilts,
        yaws_deg=parse_numbers(args.yaws, "--yaws"),
        noise_draws=args.draws,
        seed=args.seed,
    )
    root = None if args.no_wildtrack else find_wildtrack(args.dataset)
    if root is None and args.dataset is not None and not args.no_wildtrack:
        raise InputError(f"{args.dataset} is not a WILDTRACK folder (no calibrations/).")
    result = run_targeting(setup)
    if root is not None:
        result["wildtrack"] = wildtrack_targeting(root)
    if tracking_scenes:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.experiments.resolution import load_named_scene
        from cblrs.experiments.targeting_scenes import tracking_effect

        scenes = {name: load_named_scene(name, args.dataset, None) for name in tracking_scenes}
        result["tracking"] = tracking_effect(scenes)
    text = targeting_report(result)
    if args.out is not None:
        figures = plot_targeting(result, args.figures or args.out)
        result["figures"] = [str(path) for path in figures]
        _write(args.out, "targeting", result, text)
    return result, text


def run_calibration_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment calibration``: (result, markdown)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.calibration import (
        CalibrationSetup,
        calibration_figure,
        calibration_report,
        run_calibration,
    )
    from cblrs.experiments.resolution import load_named_scene

    counts = parse_numbers(args.counts, "--counts")
    seeds = parse_numbers(args.seeds, "--seeds")
    if not all(isinstance(count, int) and count >= 4 for count in counts):
        raise UsageError(
            f"--counts must be whole numbers >= 4 (a homography needs 4), got {args.counts!r}."
        )
    if not all(isinstance(seed, int) and seed >= 0 for seed in seeds):
        raise UsageError(f"--seeds must be whole numbers >= 0, got {args.seeds!r}.")
    if not (args.noise_px >= 0):
        raise UsageError(f"--noise-px must be >= 0, got {args.noise_px}.")
    if args.point_frames < 1:
        raise UsageError(f"--point-frames must be >= 1, got {args.point_frames}.")
    for option, value in (("--click-px", args.click_px), ("--ground-m", args.ground_m)):
        if not (value > 0 and math.isfinite(value)):
            raise UsageError(f"{option} must be a positive number, got {value}.")
    scene = load_named_scene("wildtrack", args.dataset, None)
    setup = CalibrationSetup(
        counts=tuple(int(count) for count in counts),
        seeds=tuple(int(seed) for seed in seeds),
        noise_px=args.noise_px,
        point_frames=args.point_frames,
        click_px=args.click_px,
        ground_m=args.ground_m,
    )
    sites: dict[tuple[int, int], Any] = {}
    result = run_calibration(scene, setup, progress=not args.quiet, sites=sites)
    text = calibration_report(result)
    if args.figures is not None or args.out is not None:
        figure = calibration_figure(scene, setup, args.figures or args.out, sites)
        result["figures"] = [str(figure)]
    if args.out is not None:
        _write(args.out, "calibration", result, text)
    return result, text


def run_counts_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment counts``: (result, markdown)."""

    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.counts import SCENES, CountsSetup, counts_report, run_counts

    scenes = tuple(name.strip() for name in args.scenes.split(",") if name.strip())
    unknown = [name for name in scenes if name not in SCENES]
    if unknown or not scenes:
        raise UsageError(f"--scenes must list some of {', '.join(SCENES)}; got {args.scenes!r}.")
    matchers = tuple(name.strip() for name in args.matchers.split(",") if name.strip())
    if not matchers or any(name not in ("fusion", "paper") for name in matchers):
        raise UsageError(f"--matchers must list fusion and/or paper, got {args.matchers!r}.")
    seeds = tuple(int(seed) for seed in parse_numbers(args.seeds, "--seeds"))
    if not (0 <= args.drop <= 1 and args.jitter >= 0):
        raise UsageError("--drop must lie in [0, 1] and --jitter be >= 0.")
    setup = CountsSetup(scenes=scenes, matchers=matchers, seeds=seeds, drop=args.drop,
                        jitter=args.jitter, sites=args.sites, wildtrack=args.dataset)
    show = not args.quiet and sys.stderr.isatty()
    result = run_counts(setup, report=(lambda line: print(line, file=sys.stderr)) if show
                        else None)
    text = counts_report(result)
    if args.out is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.experiments.counts import plot_counts

        result["figures"] = [str(path) for path in plot_counts(result, setup,
                                                               args.figures or args.out)]
        _write(args.out, "counts", result, text)
    return result, text


def run_tracking_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment tracking``: (result, markdown)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.tracking import (
        SCENES,
        WITHOUT_RULES,
        TrackingSetup,
        default_cases,
        run_tracking,
        tracking_report,
    )

    names = tuple(name.strip() for name in args.scenes.split(",") if name.strip())
    unknown = [name for name in names if name not in SCENES]
    if unknown:
        raise UsageError(f"--scenes must list some of {', '.join(SCENES)}; got {args.scenes!r}.")
    cases = tuple(case for case in default_cases()
                  if (not names or case.scene in names)
                  and not (args.no_held_out and case.held_out))
    if not cases:
        raise UsageError("no case left to run; check --scenes and --no-held-out.")
    setup = TrackingSetup(cases=cases, wildtrack=args.dataset, multiviewx=args.multiviewx,
                          model=args.model, sites=args.sites,
                          matcher_options=WITHOUT_RULES if args.without_rules else ())
    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    if jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {args.jobs}.")
    show = not args.quiet and sys.stderr.isatty()
    result = run_tracking(setup, report=(lambda line: print(line, file=sys.stderr)) if show
                          else None, jobs=jobs)
    text = tracking_report(result)
    if args.out is not None:
        _write(args.out, "tracking_without_rules" if args.without_rules else "tracking", result,
               text)
    return result, text


def run_resolution_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Entry point of ``cblrs experiment resolution``."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.resolution import (
        load_named_scene,
        plot_resolution,
        resolution_report,
        run_resolution,
    )

    sizes = tuple(float(value) for value in parse_numbers(args.sizes, "--sizes"))
    bits = tuple(int(value) for value in parse_numbers(args.bits, "--bits"))
    if any(value not in (8, 16) for value in bits):
        raise UsageError(f"--bits must be 8 and/or 16, got {args.bits!r}.")
    if any(value <= 0 for value in sizes):
        raise UsageError(f"--sizes must be positive, got {args.sizes!r}.")
    if args.frames is not None and args.frames <= 0:
        raise UsageError(f"--frames must be a positive integer, got {args.frames}.")
    names = [name.strip() for name in args.scenes.split(",") if name.strip()]
    known = {"wildtrack", "plaza", "roundabout"}
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise UsageError(
            f"--scenes must name some of {', '.join(sorted(known))}; got {args.scenes!r}."
        )
    scenes = {name: load_named_scene(name, args.dataset, args.frames) for name in names}
    result = run_resolution(scenes, sizes, bits)
    text = resolution_report(result)
    if args.out is not None:
        result["figures"] = [str(plot_resolution(result, args.figures or args.out))]
        _write(args.out, "resolution", result, text)
    return result, text


def run_pseudo_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment pseudo``: (result, markdown)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.pseudo import PseudoAttackSetup, pseudo_attack_report, run_pseudo_attack
    from cblrs.experiments.resolution import load_named_scene

    landmarks = parse_numbers(args.landmarks, "--landmarks")
    if not all(isinstance(count, int) and count >= 2 for count in landmarks):
        raise UsageError(f"--landmarks must be whole numbers >= 2, got {args.landmarks!r}.")
    sigmas = parse_numbers(args.sigmas, "--sigmas")
    mast_sigmas = parse_numbers(args.mast_sigmas, "--mast-sigmas")
    if not all(value >= 0 for value in (*sigmas, *mast_sigmas)):
        raise UsageError("--sigmas and --mast-sigmas must be numbers >= 0.")
    if args.draws < 1 or args.keys < 1:
        raise UsageError("--draws and --keys must be at least 1.")
    setup = PseudoAttackSetup(
        landmarks=tuple(int(count) for count in landmarks),
        sigmas_m=tuple(float(value) for value in sigmas),
        mast_sigmas_m=tuple(float(value) for value in mast_sigmas),
        draws=args.draws, keys=args.keys, seed=args.seed,
    )
    scene = load_named_scene("wildtrack", args.dataset, None)
    result = run_pseudo_attack(scene, setup)
    text = pseudo_attack_report(result)
    if args.out is not None:
        _write(args.out, "pseudo", result, text)
    return result, text


def run_planes_command(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Run ``cblrs experiment planes``: (result, markdown)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.experiments.planes import PlanesSetup, planes_report, run_planes

    seeds = parse_numbers(args.seeds, "--seeds") if args.seeds.strip() else ()
    if not all(isinstance(seed, int) for seed in seeds):
        raise UsageError(f"--seeds must be whole numbers, got {args.seeds!r}.")
    if not (0 <= args.drop <= 1 and args.jitter >= 0):
        raise UsageError("--drop must lie in [0, 1] and --jitter be >= 0.")
    if args.people < 0 or args.cars < 0 or args.spawn < 0:
        raise UsageError("--people, --cars and --spawn must be >= 0.")
    if not (args.max_trip > 0 and args.fps > 0):
        raise UsageError("--max-trip and --fps must be > 0.")
    setup = PlanesSetup(seed=args.seed, detector_seeds=tuple(int(seed) for seed in seeds),
                        drop=args.drop, jitter=args.jitter, people=args.people, cars=args.cars,
                        spawn_s=args.spawn, max_trip_m=args.max_trip, fps=args.fps)
    show = not args.quiet and sys.stderr.isatty()
    result = run_planes(setup, report=(lambda line: print(line, file=sys.stderr)) if show
                        else None)
    text = planes_report(result)
    if args.out is not None:
        _write(args.out, "planes", result, text)
    return result, text


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs experiment`` with its parsed arguments; the exit code."""
    if args.experiment == "targeting":
        result, text = run_targeting_command(args)
    elif args.experiment == "calibration":
        result, text = run_calibration_command(args)
    elif args.experiment == "counts":
        result, text = run_counts_command(args)
    elif args.experiment == "resolution":
        result, text = run_resolution_command(args)
    elif args.experiment == "tracking":
        result, text = run_tracking_command(args)
    elif args.experiment == "pseudo":
        result, text = run_pseudo_command(args)
    elif args.experiment == "planes":
        result, text = run_planes_command(args)
    else:  # pragma: no cover - argparse restricts the choices
        raise UsageError(f"unknown experiment {args.experiment!r}.")
    if args.json:
        print_json(result)
    else:
        print(text)
    return 0
