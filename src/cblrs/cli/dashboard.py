"""``cblrs dashboard``: the live web dashboard (and replay of a stored run, calibration page)."""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys
from pathlib import Path

from cblrs.cli.camera import add_mqtt_options, mqtt_settings
from cblrs.cli.common import InputError, UsageError, add_output_options

logger = logging.getLogger(__name__)


def register(subparsers) -> None:
    """Add the ``cblrs dashboard`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "dashboard",
        help="serve the live dashboard: site map, tracks, counts, cameras; replay; calibration",
        description=(
            "Serve a web page with the site map (or a metric grid), the live global tracks "
            "with short trails, cameras and their fields of view, zones and counting lines "
            "with live counts, per-camera status and the analytics events, read from the "
            "broker as the read-only viewer (--broker, --username viewer --password-file); "
            "with --db, replay a matcher's stored run at 1x-10x; /calibrate: click point "
            "pairs between a camera's frame and the site map, see the errors live, save to "
            "the site file and render the reference. Nothing is downloaded: the page is "
            "shipped with cblrs."
        ),
    )
    parser.add_argument("--site", type=Path, required=True, help="the site file")
    parser.add_argument("--plane", type=int, help="plane shown (default: the site's first)")
    parser.add_argument("--db", type=Path, help="a matcher's database to replay (read-only)")
    parser.add_argument(
        "--key", type=Path, help="the site's pseudo-coordinate key (docs/privacy.md): the "
        "matcher works on a pseudo site; show its tracks and events on this real site's map"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on")
    parser.add_argument("--port", type=int, default=8080, help="port (0: a free one)")
    parser.add_argument("--frames", type=Path, help="folder of camera frames <camera>.png|jpg "
                        "for the calibration page")
    parser.add_argument("--references", type=Path,
                        help="where the calibration page writes references (default: "
                        "references/ beside the site file)")
    add_mqtt_options(parser)
    add_output_options(parser)
    parser.set_defaults(broker=None, handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs dashboard`` with its parsed arguments; the exit code."""
    try:
        # optional extra: pip install cblrs[dashboard]
        import uvicorn

        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.dashboard.app import DashboardConfig, create_app
    except ImportError:
        raise UsageError(
            "the dashboard needs Starlette and uvicorn: pip install cblrs[dashboard]."
        ) from None
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.dashboard.feed import LiveFeed
    from cblrs.dashboard.replay import StoreReplay
    from cblrs.runtime.transport import TransportError

    if not args.site.is_file():
        raise InputError(f"--site {args.site} does not exist.")
    if args.frames is not None and not args.frames.is_dir():
        raise InputError(f"--frames {args.frames} is not a folder.")
    config = DashboardConfig(args.site, args.plane, database=args.db, frames=args.frames,
                             references=args.references)
    if args.key is not None:
        if config.site.pseudo_key_id is not None:
            raise UsageError(
                f"{args.site} is a pseudo site; --key goes with the real site (its map), to "
                "show a pseudo matcher's tracks where they are."
            )
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.privacy import PseudoKey

        config.to_site = PseudoKey.load(args.key).to_site
    plane = args.plane
    if plane is None:
        planes = config.site.planes
        plane = planes.ids[0] if planes is not None else 1
    elif config.site.planes is not None and plane not in config.site.planes.ids:
        raise UsageError(f"--plane {plane} is not a plane of {args.site.name} "
                         f"(planes {config.site.planes.ids}).")
    config.plane_id = plane
    if args.db is not None:
        StoreReplay(args.db).close()  # a file that cannot be replayed says so now
    listener = _listen(args.host, args.port)
    feed = None
    if args.broker is not None:
        settings = mqtt_settings(args)
        client_id = args.client_id or f"cblrs-dashboard-{socket.gethostname()}-{plane}"
        if not logging.getLogger().isEnabledFor(logging.DEBUG):
            # A refusal is said once, below, as one sentence; not also as a log line.
            logging.getLogger("cblrs.runtime.mqtt_transport").setLevel(logging.ERROR)
        feed = LiveFeed(settings, plane, client_id[:64], to_site=config.to_site)
        try:
            feed.start()
        except TransportError as error:
            listener.close()
            who = f"user {args.username!r}" if args.username else "an anonymous client"
            reason = str(error).rsplit(": ", 1)[-1].rstrip(".")
            raise UsageError(
                f"the broker at {args.broker} did not accept the dashboard as {who} ({reason}); "
                "check --broker, --username and --password-file (the broker's viewer)."
            ) from None
        config.feed = feed
        config.broker = args.broker
    host, port = listener.getsockname()[:2]
    where = [f"site {args.site}", f"plane {plane}"]
    if feed is not None:
        where.append(f"live from {args.broker}" + (f" as {args.username}" if args.username
                                                    else ""))
    if args.db is not None:
        where.append(f"replay of {args.db}")
    if feed is None and args.db is None:
        where.append("no --broker nor --db: site map and calibration page only")
    if args.json:
        print(json.dumps({"url": f"http://{host}:{port}/", "site": str(args.site),
                          "plane": plane, "broker": args.broker,
                          "db": None if args.db is None else str(args.db)}), flush=True)
    else:
        print(f"dashboard on http://{host}:{port}/ ({', '.join(where)}); Ctrl-C stops it",
              flush=True)
    server = uvicorn.Server(uvicorn.Config(create_app(config), log_level="warning",
                                           access_log=False, lifespan="off"))
    try:
        server.run(sockets=[listener])
    finally:
        if feed is not None:
            feed.close()
        listener.close()
    print("dashboard stopped", file=sys.stderr)
    return 0


def _listen(host: str, port: int) -> socket.socket:
    """A bound, listening socket (one sentence when the address cannot be used)."""
    try:
        info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        listener = socket.socket(info[0], socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(info[4])
        listener.listen(128)
    except OSError as error:
        raise UsageError(
            f"cannot serve on {host}:{port}: {error.strerror or error}; choose another --port."
        ) from None
    return listener
