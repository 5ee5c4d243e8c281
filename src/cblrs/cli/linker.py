"""``cblrs linker``: the site's linker service (every plane's tracks -> global ids, counts)."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cblrs.cli.backbone import add_backbone_options, nats_settings, uses_nats
from cblrs.cli.common import UsageError, check_non_negative, check_positive, print_json
from cblrs.cli.mqtt_options import add_mqtt_options, mqtt_settings
from cblrs.cli.stopping import install_stop_handlers


def register(subparsers) -> None:
    """Add the ``cblrs linker`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "linker",
        help="run the site's linker: every plane's tracks -> global ids and site counts",
        description=(
            "Subscribe to every plane's track updates (cblrs/<plane>/tracks: MQTT with a "
            "persistent session, or on NATS the linker's durable consumer on each plane's "
            "tracks stream, named after --client-id), give each track one global id "
            "across planes (the site file's links), count the site's places on the global "
            "tracks, keep everything in a SQLite file (--db) and publish the global tracks on "
            "cblrs/0/tracks, the site's events on cblrs/0/events and its live counts on "
            "cblrs/0/live. Restarting on the same --db resumes where it stopped (killed too: "
            "the backbone keeps what came meanwhile). With --stats DB, print the counters "
            "stored in DB and exit; with --prepare, create the linker's session or consumers "
            "and exit."
        ),
    )
    parser.add_argument("--stats", type=Path, metavar="DB", help="print a database's counters")
    parser.add_argument(
        "--prepare", action="store_true",
        help="create the linker's persistent session (MQTT) or, with the NATS admin's login, "
        "every plane's tracks stream and the consumers of the linker named by --client-id, "
        "then exit: the backbone keeps the planes' tracks for it from then on")
    parser.add_argument("--site", type=Path, metavar="SITE.yaml",
                        help="site file with planes, links and places")
    parser.add_argument("--db", type=Path,
                        help="SQLite file of the linker (created if missing; its folder must "
                        "exist)")
    parser.add_argument("--delay", type=float, default=0.5, metavar="SECONDS",
                        help="rows wait this long behind the oldest plane's clock")
    parser.add_argument("--max-wait", type=float, default=30.0, metavar="SECONDS",
                        help="a plane silent this long while others go on is left out of the "
                        "watermark (its later rows for linked times count as late)")
    parser.add_argument("--decision", type=float, default=1.0, metavar="SECONDS",
                        help="a track that starts in a hand-over region is watched this long "
                        "before its id is decided")
    parser.add_argument("--no-analytics", action="store_true",
                        help="do not count the site's places on the global tracks")
    parser.add_argument("--live-interval", type=float, default=1.0, metavar="SECONDS",
                        help="seconds between live summaries on cblrs/0/live (0: none)")
    parser.add_argument("--out-tracks", type=Path,
                        help="write the global tracks (AI City format) when it stops")
    stopping = parser.add_argument_group("stopping (default: run until SIGINT / SIGTERM)")
    stopping.add_argument("--idle-exit", type=float, metavar="SECONDS",
                          help="after this long without track updates, end every stream "
                          "(decide, emit and count everything) and stop (replays, tests)")
    add_mqtt_options(parser)
    add_backbone_options(parser, matcher=False)
    parser.add_argument("--json", action="store_true", help="print the final summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.set_defaults(handler=run)


def show_stats(path: Path, as_json: bool) -> int:
    """Print the counters of a linker database."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.outputs.linker_store import LinkerStore

    with LinkerStore(path, read_only=True) as store:
        summary: dict[str, Any] = {"database": str(path), **store.counters(),
                                   "plane_clocks": store.plane_clocks()}
    if as_json:
        print_json(summary)
    else:
        print(", ".join(f"{key} {value}" for key, value in summary.items()))
    return 0


def linker_transport(args: argparse.Namespace, client_id: str, will: Any,
                     planes: Sequence[int], replay: bool = False) -> Any:
    """The linker's transport: MQTT with a persistent session, or on NATS its durable
    consumer on every plane's tracks stream (``replay``: from the streams' first messages,
    for an empty database)."""
    if uses_nats(args):
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.runtime.transport.nats_fanin import NatsFanIn, linker_consumer

        # --prepare (with the admin's login) creates the streams and consumers; a linker's
        # own login may not (see docs/security.md).
        settings = nats_settings(args, publish_window=64,
                                 manage=True if args.prepare else None)
        return NatsFanIn(client_id, settings, durable=linker_consumer(client_id),
                         planes=planes, replay=replay, will=will)
    from cblrs.runtime.transport.mqtt_transport import MqttTransport

    return MqttTransport(client_id, mqtt_settings(args), persistent=True, will=will)


def prepare(args: argparse.Namespace, linker_id: str, planes: Sequence[int]) -> int:
    """``--prepare``: create the linker's session or consumers, deliver nothing, exit."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.transport.topics import tracks_topic

    transport = linker_transport(args, linker_id, None, planes)
    for plane in planes:
        # Not acknowledged: whatever comes now is delivered again to the linker.
        transport.subscribe(tracks_topic(plane), lambda delivery: None, qos=1)
    transport.connect()
    transport.close()
    if not args.quiet:
        print(f"prepared: the backbone keeps planes {', '.join(map(str, planes))}' tracks for "
              f"linker {linker_id} from now on", file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs linker`` with its parsed arguments; the exit code."""
    if args.stats is not None:
        return show_stats(args.stats, args.json)
    if args.site is None or (args.db is None and not args.prepare):
        raise UsageError("give --site SITE and --db FILE (or --stats DB).")
    if args.prepare and uses_nats(args) and args.username and not args.client_id:
        raise UsageError("--prepare with the admin's login: give --client-id LINKER, the "
                         "linker whose consumers it creates.")
    check_non_negative(args.delay, "--delay")
    check_positive(args.max_wait, "--max-wait")
    check_non_negative(args.decision, "--decision")
    check_non_negative(args.live_interval, "--live-interval")
    if args.idle_exit is not None:
        check_positive(args.idle_exit, "--idle-exit")
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.linking.files import site_analytics_config
    from cblrs.linking.linker import LinkerConfig, PlaneLinker
    from cblrs.runtime.outputs.linker_service import LinkerService
    from cblrs.runtime.outputs.linker_store import LinkerStore
    from cblrs.runtime.transport.protocol import Will
    from cblrs.runtime.transport.topics import linker_status_topic, validate_client_id
    from cblrs.runtime.wire import encode_status
    from cblrs.site import load_site

    site = load_site(args.site)
    planes = site.require_planes("the linker")
    if not site.links:
        raise UsageError(f"{args.site} has no links between its planes (links: in the site "
                         "file), so there is nothing to link.")
    linker = PlaneLinker(planes, site.links, LinkerConfig(decision_s=args.decision))
    analytics = None
    if len(site.places) and not args.no_analytics:
        from cblrs.analytics.site import with_site_time
        from cblrs.runtime.outputs.online_analytics import OnlineAnalytics

        config = with_site_time(site_analytics_config(site.links), site)
        analytics = OnlineAnalytics(site.places, config, delay_s=0.0)
    linker_id = validate_client_id(args.client_id or args.username or "linker", "client id")
    will = Will(linker_status_topic(linker_id), encode_status(linker_id, "offline",
                                                              role="linker"))
    if args.prepare:
        return prepare(args, linker_id, planes.ids)
    store = LinkerStore(args.db)
    # An empty database links from the streams' first messages (a consumer that served
    # another database before has passed them).
    replay = store.linker_state() is None
    service = LinkerService(
        linker_transport(args, linker_id, will, planes.ids, replay), store, linker, planes.ids,
        site={"planes": planes.to_list(), "links": [link.to_dict() for link in site.links]},
        analytics=analytics, delay_s=args.delay, max_wait_s=args.max_wait,
        linker_id=linker_id, live_interval_s=args.live_interval or None,
    )
    stop = threading.Event()
    install_stop_handlers(stop.set)
    try:
        service.start()
    except BaseException:
        store.close()
        raise
    if not args.quiet:
        print(f"linker {linker_id}: planes {', '.join(map(str, planes.ids))}, "
              f"{len(site.links)} links, db {args.db}"
              + (f"; counting {len(site.places)} places" if analytics is not None else ""),
              file=sys.stderr)
    finished = False
    try:
        while not stop.wait(0.2):
            if service.failed() is not None:
                break
            idle = time.monotonic() - service.last_activity
            if args.idle_exit is not None and idle > args.idle_exit:
                finished = True
                break
        service.close(finish=finished)
    finally:
        summary = service.stats()
        if args.out_tracks is not None:
            from cblrs.datasets.aicity import write_tracks

            write_tracks(args.out_tracks, store.rows().tracks)
            summary["out_tracks"] = str(args.out_tracks)
        store.close()
    summary["stopped_by"] = "idle" if finished else "signal"
    if args.json:
        print_json(summary)
    else:
        print(", ".join(f"{key} {value}" for key, value in summary.items()
                        if not isinstance(value, dict)))
    return 0
