"""``cblrs matcher``: the central matcher service of one plane (MQTT in, SQLite out)."""

from __future__ import annotations

import argparse
import functools
import gc
import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

from cblrs.cli.backbone import add_backbone_options, matcher_transport, uses_nats
from cblrs.cli.common import (
    InputError,
    UsageError,
    check_non_negative,
    check_positive,
    print_json,
)
from cblrs.cli.late_options import add_late_options, camera_fps, retrack_policy
from cblrs.cli.metrics_http import add_http_options, http_settings
from cblrs.cli.mqtt_options import add_mqtt_options, mqtt_settings
from cblrs.errors import CblrsError

logger = logging.getLogger(__name__)


def register(subparsers) -> None:
    """Add the ``cblrs matcher`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "matcher",
        help="run the central matcher of one plane: MQTT -> validate -> track -> SQLite",
        description=(
            "Subscribe to cblrs/<plane>/+/detections (persistent session, QoS 1), validate, "
            "de-duplicate, order by capture time, track, and store everything in a SQLite file "
            "(--db). Restarting with the same --db and --client-id resumes where it stopped. "
            "One matcher serves a plane at a time (a second one is refused). With --stats DB, "
            "print the counters stored in DB and exit; with --prepare, create the matcher's "
            "session on the broker (so it keeps the plane's messages) and exit. SIGTERM or "
            "SIGINT stop it cleanly: summary, --out-tracks, exit 0."
        ),
    )
    parser.add_argument("--stats", type=Path, metavar="DB", help="print a database's counters")
    parser.add_argument(
        "--db", type=Path,
        help="SQLite file of this matcher (created if missing; its folder must exist)",
    )
    parser.add_argument(
        "--prepare", action="store_true",
        help="subscribe once (creating the persistent session and the database) and exit: "
        "run it before any camera starts",
    )
    parser.add_argument(
        "--new-db", action="store_true",
        help="serve the plane from this database although another one served it last",
    )
    parser.add_argument(
        "--references",
        type=Path,
        help="folder of the cameras' reference PNGs (gives camera ids and planes)",
    )
    parser.add_argument(
        "--site",
        type=Path,
        help="site file: camera ids, planes, camera positions (for the fusion tracker) and "
        "places; with --references too, the references must be rendered for its planes",
    )
    parser.add_argument(
        "--cameras", help="comma-separated camera ids, in this order (default: --references)"
    )
    parser.add_argument("--plane", type=int, help="plane id (default: the references' only plane)")
    parser.add_argument("--matcher", default="fusion", help="fusion (default) or paper")
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="matcher option (repeatable); VALUE is JSON or a string",
    )
    parser.add_argument(
        "--window",
        type=float,
        default=2.0,
        help="ordering window, seconds: how long a timestamp waits for a silent camera",
    )
    parser.add_argument("--out-tracks", type=Path, help="also write tracks (AI City format; "
                        "its .meta.json keeps the capture times, for cblrs analytics)")
    parser.add_argument(
        "--no-publish-tracks", action="store_true", help="do not publish on cblrs/<plane>/tracks"
    )
    validation = parser.add_argument_group("validation")
    validation.add_argument(
        "--max-age",
        type=float,
        help="reject capture times older than this, seconds (default 1 day)",
    )
    validation.add_argument(
        "--max-future", type=float, help="reject capture times ahead by more, seconds (default 60)"
    )
    validation.add_argument("--max-bytes", type=int, help="largest accepted payload, bytes")
    stopping = parser.add_argument_group("stopping (default: run until SIGINT / SIGTERM)")
    stopping.add_argument(
        "--idle-exit",
        type=float,
        metavar="SECONDS",
        help="stop after this long without detections (replays, tests)",
    )
    stopping.add_argument(
        "--until-cameras-offline",
        action="store_true",
        help="stop once every camera has published its final 'offline' status",
    )
    stopping.add_argument(
        "--offline-after",
        type=float,
        metavar="SECONDS",
        help="with --until-cameras-offline: only an 'offline' published after this time "
        "(seconds since 1970) counts, not an earlier run's (cblrs up gives its start)",
    )
    parser.add_argument(
        "--stats-interval", type=float, metavar="SECONDS", help="log counters every N seconds"
    )
    retention = parser.add_argument_group(
        "retention", "history kept in --db (never a message not yet tracked; --out-tracks "
        "writes what is kept)")
    retention.add_argument(
        "--retain-hours", type=float, default=24.0,
        help="delete inbox, track, published event and binned count rows older than this "
        "(default 24; 0: no age limit; the counts' totals are kept)")
    retention.add_argument(
        "--retain-gb", type=float, default=4.0,
        help="keep the database under this size, GiB, oldest rows first (default 4; 0: none)")
    add_late_options(parser)
    online = parser.add_argument_group("analytics, live summary and metrics")
    online.add_argument(
        "--no-analytics",
        action="store_true",
        help="do not count the site's places (default with --site places: count them, "
        "publish events on cblrs/<plane>/events and keep the counts in --db)",
    )
    online.add_argument(
        "--analytics-delay",
        type=float,
        default=0.5,
        metavar="SECONDS",
        help="rows wait this long (plus the tracker's own lag) behind the newest capture "
        "time before they are counted",
    )
    add_http_options(online)
    online.add_argument(
        "--live-interval",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="seconds between live summaries on cblrs/<plane>/live (0: none)",
    )
    add_mqtt_options(parser)
    add_backbone_options(parser, matcher=True)
    parser.add_argument("--json", action="store_true", help="print the final summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    # SIGTERM: a clean stop; ended by a watchdog (exit 1) after 25 s (cblrs up waits 30 s)
    parser.set_defaults(handler=run, stop_signals=(25.0, 1))


def parse_options(items: list[str]) -> dict[str, Any]:
    """``--option KEY=VALUE`` items as matcher options (values parsed as JSON when they are)."""
    options: dict[str, Any] = {}
    for item in items:
        key, separator, value = item.partition("=")
        if not separator or not key:
            raise UsageError(f"--option {item!r} must be KEY=VALUE.")
        try:
            options[key] = json.loads(value)
        except ValueError:
            options[key] = value
    return options


def read_references(folder: Path) -> tuple[list[str], Any, dict[str, list[int]], dict]:
    """Camera ids (file-name order), the planes of a folder of reference PNGs, each camera's
    plane ids (a site's cameras may each hold only their own plane), and the images by path
    (for the tracker's views: a 16-bit PNG takes a tenth of a CPU-second to decode)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.plane import PlaneSet
    from cblrs.reference import ReferenceImage

    if not folder.is_dir():
        raise InputError(f"--references {folder} is not a folder.")
    paths = sorted(path for path in folder.glob("*.png") if not path.stem.endswith("_preview"))
    if not paths:
        raise UsageError(f"{folder} holds no reference PNGs; render them with `cblrs render`.")
    names: list[str] = []
    known: dict[int, Any] = {}
    camera_planes: dict[str, list[int]] = {}
    images: dict[Path, Any] = {}
    for path in paths:
        reference = images[path] = ReferenceImage.load(path)
        name = reference.camera_name or path.stem
        names.append(name)
        camera_planes[name] = reference.planes.ids
        for plane in reference.planes:
            if known.setdefault(plane.plane_id, plane) != plane:
                raise UsageError(f"{path} was rendered for other planes than {paths[0]}.")
    try:
        planes = PlaneSet(known.values())
    except CblrsError as error:
        raise UsageError(f"the references in {folder} do not fit together: {error}") from None
    return names, planes, camera_planes, images


def check_arguments(args: argparse.Namespace) -> None:
    """One sentence for every option value that makes no sense (before anything starts)."""
    check_non_negative(args.window, "--window")
    if args.max_age is not None:
        check_positive(args.max_age, "--max-age")
    if args.max_future is not None:
        check_non_negative(args.max_future, "--max-future")
    if args.max_bytes is not None and args.max_bytes <= 0:
        raise UsageError(f"--max-bytes must be a positive number of bytes, got {args.max_bytes}.")
    if args.idle_exit is not None:
        check_positive(args.idle_exit, "--idle-exit")
    if args.stats_interval is not None:
        check_positive(args.stats_interval, "--stats-interval")
    check_non_negative(args.retain_hours, "--retain-hours")
    check_non_negative(args.retain_gb, "--retain-gb")
    retrack_policy(args), camera_fps(args)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs matcher`` with its parsed arguments; the exit code."""
    if args.stats is not None:
        from cblrs.cli.matcher_stats import show_stats

        return show_stats(args.stats, args.json)
    if args.db is None or (args.references is None and args.site is None):
        raise UsageError("give --db FILE and --references DIR or --site SITE (or --stats DB).")
    check_arguments(args)
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.matching import make_matcher
    from cblrs.runtime.matcher.matcher_service import MatcherService
    from cblrs.runtime.matcher.retention import RetentionPolicy
    from cblrs.runtime.matcher.store import RuntimeStore
    from cblrs.runtime.matcher.views import tell_views
    from cblrs.runtime.transport.mqtt_transport import MqttTransport
    from cblrs.runtime.transport.protocol import Will
    from cblrs.runtime.transport.topics import matcher_status_topic, validate_client_id
    from cblrs.runtime.wire import ValidationPolicy, encode_status

    site = None
    if args.site is not None:
        from cblrs.site import load_site  # lazy, as above

        site = load_site(args.site)
    images: dict[Path, Any] = {}
    if args.references is not None:
        names, planes, camera_planes, images = read_references(args.references)
        site_planes = {} if site is None or site.planes is None else {
            plane.plane_id: plane for plane in site.planes}
        if site_planes and any(site_planes.get(plane.plane_id) != plane for plane in planes):
            raise UsageError(
                f"the references in {args.references} were rendered for other planes than "
                f"{args.site.name}'s; render them with `cblrs render --site {args.site}`."
            )
    else:
        assert site is not None
        planes = site.require_planes("the matcher")
        names = [camera.name for camera in site.require_cameras("the matcher")]
        camera_planes = {name: site.camera_planes(name).ids for name in names}
    plane_id = args.plane
    if plane_id is None:
        if len(planes.ids) != 1:
            raise UsageError(f"the references have planes {planes.ids}; choose one with --plane.")
        plane_id = planes.ids[0]
    elif plane_id not in planes.ids:
        raise UsageError(f"--plane {plane_id} is not in the references (planes {planes.ids}).")
    # The plane's cameras: those whose reference holds it (a site camera may hold only its own).
    names = [name for name in names if plane_id in camera_planes[name]]
    if args.cameras:
        wanted = [name.strip() for name in args.cameras.split(",") if name.strip()]
        unknown = sorted(set(wanted) - set(names))
        if unknown:
            raise UsageError(f"no reference image of plane {plane_id} for camera(s) "
                             f"{', '.join(unknown)}.")
        names = wanted
    options = parse_options(args.option)
    positions = site_positions(site, names)
    if site is not None and args.matcher == "fusion" and "camera_positions" not in options:
        # Noise grows with distance and along the ray (without: WILDTRACK HOTA 92.0 vs 93.8).
        if positions:
            options["camera_positions"] = {name: list(xyz) for name, xyz in positions.items()}
    matcher = make_matcher(args.matcher, planes, names, **options)
    limits: dict[str, Any] = {"bits": planes.bits}
    for name, value in (
        ("max_age_s", args.max_age),
        ("max_future_s", args.max_future),
        ("max_bytes", args.max_bytes),
    ):
        if value is not None:
            limits[name] = value
    policy = ValidationPolicy(**limits)
    # The matcher id is its MQTT client id (the persistent session) and names its status
    # topic; the broker's ACL grants that topic to the user of the same name.
    matcher_id = validate_client_id(
        args.client_id or args.username or f"matcher{plane_id}", "client id"
    )
    status_topic = matcher_status_topic(plane_id, matcher_id)
    will = Will(status_topic, encode_status(matcher_id, "offline", role="matcher"))
    stop = threading.Event()
    failures: list[str] = []
    analytics = make_analytics(site, plane_id, args)
    alerts, senders = None, {}
    if site is not None:  # lazy: a site has imported the alerts' models already
        from cblrs.runtime.outputs.alert_service import site_alerts

        alerts, senders = site_alerts(site)  # the webhooks' secrets are read now
    metrics = server = None
    if args.http is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.runtime.matcher.metrics import MetricsServer, ServiceMetrics

        address, http_token = http_settings(args)
        metrics = ServiceMetrics(plane_id, names)
    tell_views(matcher, names, args.references, site, images)  # where each camera sees the ground
    store = RuntimeStore(args.db)
    if uses_nats(args):
        # An empty store is rebuilt from the plane's stream (e.g. on a new host).
        rebuild = store.released_timestamp() is None and not store.status_counts()
        transport = matcher_transport(
            args, matcher_id, plane_id, rebuild=rebuild, will=will,
            on_failure=functools.partial(_failed, failures, stop),
        )
    else:
        transport = MqttTransport(matcher_id, mqtt_settings(args), persistent=True, will=will)
    service = MatcherService(
        transport,
        store,
        matcher,
        plane_id,
        names,
        policy=policy,
        window_s=args.window,
        publish_tracks=not args.no_publish_tracks,
        settings={"matcher": args.matcher, "options": options},
        allow_other_database=args.new_db,
        retention=RetentionPolicy(
            max_age_s=args.retain_hours * 3600 if args.retain_hours > 0 else None,
            max_bytes=int(args.retain_gb * 2**30) if args.retain_gb > 0 else None,
        ),
        analytics=analytics,
        metrics=metrics,
        live_interval_s=args.live_interval or None,
        retrack=retrack_policy(args), alerts=None if args.prepare else alerts,
        alert_senders=senders, camera_fps=camera_fps(args))
    if metrics is not None:

        def exposition() -> bytes:
            metrics.set_buffered(service.buffered())
            metrics.set_takeovers(int(getattr(transport, "takeovers", 0)))
            return metrics.exposition()

        try:
            server = MetricsServer(address, exposition, service.health, service.ready,
                                   token=http_token).start()
        except Exception:
            store.close()
            raise
    started = time.perf_counter()
    # What is alive now (modules, the matcher) stays for the life of the process: keep it out
    # of the garbage collector's full passes, which otherwise pause every thread for tens of
    # milliseconds while messages wait.
    gc.freeze()
    if hasattr(transport, "open"):
        try:
            transport.open()  # NATS: the plane's lease before the store is touched
        except BaseException:
            store.close()
            raise
    try:
        # Connects, holds the database and the plane's lease, then starts the tracker
        # process: a refusal (wrong password, another matcher) ends here with one sentence.
        service.start(on_started=lambda: args.signals.arm(stop.set))
    except BaseException:
        try:
            service.stop()
        except Exception:  # the start failure is what the user needs to read
            pass
        clear_will = getattr(transport, "clear_will", None)
        if clear_will is not None:
            clear_will()  # it never said "online": say nothing about the plane
        transport.close(unclean=False, timeout=1.0)
        store.close()
        raise
    args.signals.arm(stop.set)  # until now a signal ends the start-up at once (cli.stopping)
    if not args.quiet:
        print(
            f"matcher {matcher_id}: plane {plane_id}, cameras {', '.join(names)}, db {args.db}"
            + (f", cameras at {args.camera_fps:g} fps at most" if args.camera_fps else "")
            + (" (preparing: exits once subscribed)" if args.prepare else ""), file=sys.stderr)
        print(position_summary(site, names, options, args.matcher), file=sys.stderr)
        if analytics is not None:
            print(f"analytics: {len(analytics.places.lines)} counting lines, "
                  f"{len(analytics.places.zones)} zones; events on cblrs/{plane_id}/events",
                  file=sys.stderr)
        if server is not None:
            print(f"metrics: {server.url}/metrics, /healthz, /readyz", file=sys.stderr)
    flush = True if args.prepare else _wait(service, stop, args)
    failure: BaseException | None = None
    try:
        service.close(flush=flush)
    except RuntimeError as error:
        failure = error.__cause__ or error
    finally:
        if server is not None:
            server.close()
        summary = service.stats()
        if args.out_tracks is not None:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.datasets.aicity import write_tracks

            write_tracks(args.out_tracks, store.tracks(), keep_timestamps=True)
            summary["out_tracks"] = str(args.out_tracks)
        store.close()
    summary["elapsed_s"] = time.perf_counter() - started
    summary["database"] = str(args.db)
    summary["stopped_by"] = "failure" if failure is not None else (
        "signal" if stop.is_set() else "prepare" if args.prepare else "condition")
    if args.json:
        print_json(summary)
    else:
        print(_one_line(summary))
    if failure is not None:
        raise MatcherFailed(f"the matcher stopped: {_first_line(failure)}")
    if failures:
        raise MatcherFailed(f"the matcher stopped: {failures[0].rstrip('.')}.")
    if args.prepare and not args.quiet:
        session_hours = getattr(getattr(transport, "settings", None), "session_expiry_s",
                                24 * 3600) // 3600
        print(
            f"prepared: the broker keeps plane {plane_id}'s messages for {matcher_id} from now "
            f"on (for {session_hours} h while it is away); start the matcher "
            "with the same --db and --client-id",
            file=sys.stderr,
        )
    return 0


class MatcherFailed(CblrsError):
    """The running matcher stopped because of a failure (printed as one sentence)."""


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    first = text[0] if text else type(error).__name__
    if first.startswith("the tracker process failed:") and len(text) > 1:
        first = f"the tracker process failed ({text[-1].strip()})"
    elif first.startswith("the tracker process failed: "):
        first = first.removeprefix("the tracker process failed: ")
    return first.rstrip(".") + "."


def _failed(failures: list[str], stop: threading.Event, reason: str) -> None:
    """The transport failed for good (e.g. lost the plane's lease): record it and stop."""
    failures.append(reason)
    stop.set()


def make_analytics(site: Any, plane_id: int, args: argparse.Namespace) -> Any:
    """The plane's online analytics: the site's places of this plane (None without)."""
    if site is None or args.no_analytics:
        return None
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.outputs.online_analytics import site_online_analytics

    return site_online_analytics(site, plane_id, args.analytics_delay)


def site_positions(site: Any, names: list[str]) -> dict[str, tuple[float, float, float]]:
    """Positions of the named cameras that the site knows (empty without a site)."""
    if site is None:
        return {}
    return {name: xyz for name, xyz in site.camera_positions().items() if name in names}


def position_summary(site: Any, names: list[str], options: dict[str, Any], matcher: str) -> str:
    """The start-up line saying which cameras have positions (and places, with a site)."""
    given = options.get("camera_positions") or {}
    if matcher != "fusion":
        text = f"camera positions: not used by the {matcher} matcher"
    elif not given:
        text = "camera positions: none (give --site so the fusion tracker knows its cameras)"
    else:
        parts = []
        for name in names:
            if name in given:
                x, y, *height = given[name]
                how = ""
                if site is not None and name in site.camera_names:
                    how = f" [{site.camera(name).position_source}]"
                parts.append(
                    f"{name} ({x:.2f}, {y:.2f}"
                    + (f", {height[0]:.2f} m high" if height else "")
                    + f"){how}"
                )
        text = f"camera positions for {len(parts)} of {len(names)} cameras: " + "; ".join(parts)
        without = [name for name in names if name not in given]
        if without:
            notes = [
                f"{name} ({site.camera(name).position_note})"
                if site is not None and name in site.camera_names
                else name
                for name in without
            ]
            text += "; without a position: " + ", ".join(notes)
    if site is not None:
        text += (
            f"\nsite {site.name or site.source}: {len(site.places.zones)} zones, "
            f"{len(site.places.lines)} counting lines, {len(site.alerts.rules)} alert rules"
        )
    return text


def _wait(service: Any, stop: threading.Event, args: argparse.Namespace) -> bool:
    """Block until a stop condition; returns whether to flush waiting groups."""
    last_stats = time.monotonic()
    settled = 0
    while not stop.wait(0.2):
        if service.failed():
            return False
        if args.stats_interval and time.monotonic() - last_stats >= args.stats_interval:
            last_stats = time.monotonic()
            print(_one_line(service.stats()), file=sys.stderr, flush=True)
        ended = args.until_cameras_offline and service.cameras_done(args.offline_after)
        if ended and service.drained():
            settled += 1
            if settled >= 3:
                return True
        else:
            settled = 0
        if args.idle_exit is not None and service.idle_seconds() >= args.idle_exit:
            return True
    return False


def _one_line(stats: dict[str, Any]) -> str:
    rejected = stats.get("rejected_by_reason") or {}
    details = ", ".join(f"{name} {value}" for name, value in sorted(rejected.items()))
    return (
        f"plane {stats['plane_id']}: received {stats['received']}, "
        f"rejected {stats['rejected']}{f' ({details})' if details else ''}, "
        f"duplicates {stats['duplicates']}, late {stats['late']}, "
        f"processed {stats['processed']}, tracks {stats['tracks']}, "
        f"buffered {stats['buffered_messages']}{_clocks_off(stats.get('clocks'))}"
    )


def _clocks_off(clocks: dict[str, Any] | None) -> str:
    """``", clock off: CAM +2.000 s"`` for cameras whose clocks are beyond the tolerance."""
    off = [f"{name} {report['offset_s']:+.3f} s" for name, report in (clocks or {}).items()
           if report["beyond_tolerance"]]
    return f", clock off: {', '.join(off)}" if off else ""
