"""``cblrs dashboard``: the live web dashboard (and replay of a stored run, calibration page)."""

from __future__ import annotations

import argparse
import json
import logging
import re
import secrets
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any

from cblrs.cli.backbone import add_backbone_options, nats_settings, uses_nats
from cblrs.cli.common import InputError, UsageError, add_output_options, check_positive
from cblrs.cli.mqtt_options import add_mqtt_options, mqtt_settings

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
            "shipped with cblrs. Everyone logs in: with --users, the users of that file "
            "(cblrs dashboard-users; viewers see, admins also calibrate); without it, on "
            "loopback only, whoever opens the login link printed at start (an admin link "
            "valid for this run). See docs/security.md. A site of several planes gets an "
            "overview (without --plane, or --plane all): every plane's map and live tracks "
            "with the linker's global ids, site-wide counts, each plane's matcher health, and "
            "each plane's own page. Reads MQTT (--broker) or NATS (--backbone nats://..., or "
            "--broker nats://...). See docs/live.md."
        ),
    )
    parser.add_argument("--site", type=Path, required=True, help="the site file")
    parser.add_argument("--plane", metavar="ID|all",
                        help="plane shown, or all: the overview of every plane (default: the "
                        "overview on a site of several planes, else its plane)")
    parser.add_argument("--db", type=Path, help="a matcher's database to replay (read-only)")
    parser.add_argument(
        "--key", type=Path, help="the site's pseudo-coordinate key (docs/privacy.md): the "
        "matcher works on a pseudo site; show its tracks and events on this real site's map"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (beyond "
                        "loopback only with --users)")
    parser.add_argument("--port", type=int, default=8080, help="port (0: a free one)")
    access = parser.add_argument_group("who may use it (docs/security.md)")
    access.add_argument("--users", type=Path, metavar="FILE",
                        help="users file written by cblrs dashboard-users (default: no users; "
                        "loopback only, with a login link for this run)")
    access.add_argument("--tls-cert", type=Path, metavar="PEM",
                        help="serve HTTPS with this certificate (chain) ...")
    access.add_argument("--tls-key", type=Path, metavar="PEM", help="... and its private key")
    access.add_argument("--origin", metavar="URL",
                        help="the address browsers use, when it is not this server's own "
                        "(e.g. https://dashboard.example.org behind a TLS proxy)")
    access.add_argument("--session-hours", type=float, default=12.0,
                        help="a login lasts this long")
    access.add_argument("--idle-minutes", type=float, default=120.0,
                        help="a login ends after this long without a request (an open page "
                        "keeps it)")
    parser.add_argument("--frames", type=Path, help="folder of camera frames <camera>.png|jpg "
                        "for the calibration page")
    parser.add_argument("--references", type=Path,
                        help="where the calibration page writes references (default: "
                        "references/ beside the site file)")
    add_mqtt_options(parser)
    add_backbone_options(parser, matcher=False)
    add_output_options(parser)
    parser.set_defaults(broker=None, handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs dashboard`` with its parsed arguments; the exit code."""
    try:
        # optional extra: pip install cblrs[dashboard]
        import uvicorn

        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.dashboard.app import DashboardConfig, create_app, server_config
    except ImportError:
        raise UsageError(
            "the dashboard needs Starlette and uvicorn: pip install cblrs[dashboard]."
        ) from None
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.dashboard.feed import LiveFeed
    from cblrs.dashboard.replay import StoreReplay
    from cblrs.runtime.transport.protocol import TransportError

    auth = _authenticator(args)
    if not args.site.is_file():
        raise InputError(f"--site {args.site} does not exist.")
    if args.frames is not None and not args.frames.is_dir():
        raise InputError(f"--frames {args.frames} is not a folder.")
    config = DashboardConfig(args.site, None, database=args.db, frames=args.frames,
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
    plane = _shown_plane(args, config)
    config.plane_id = plane
    config.overview = plane is None
    if args.db is not None:
        StoreReplay(args.db).close()  # a file that cannot be replayed says so now
    _backbone(args)
    listener = _listen(args.host, args.port)
    feed = None
    if args.broker is not None or args.backbone is not None:
        nats = args.backbone is not None
        settings = nats_settings(args) if nats else mqtt_settings(args)
        shown = "all" if plane is None else plane
        client_id = args.client_id or f"cblrs-dashboard-{socket.gethostname()}-{shown}"
        if not logging.getLogger().isEnabledFor(logging.DEBUG):
            # A refusal is said once, below, as one sentence; not also as a log line.
            for name in ("cblrs.runtime.transport.mqtt_transport",
                         "cblrs.runtime.transport.nats_transport"):
                logging.getLogger(name).setLevel(logging.ERROR)
        feed = LiveFeed(settings, config.planes if plane is None else plane, client_id[:64],
                        to_site=config.to_site)
        try:
            feed.start()
        except TransportError as error:
            feed.close()
            listener.close()
            who = f"user {args.username!r}" if args.username else "an anonymous client"
            reason = str(error).rsplit(": ", 1)[-1].rstrip(".")
            where = args.backbone or args.broker
            raise UsageError(
                f"the {'NATS servers' if nats else 'broker'} at {where} did not accept the "
                f"dashboard as {who} ({reason}); check --{'backbone' if nats else 'broker'}, "
                "--username, --password-file" + (" and --site-id" if nats else "")
                + " (the backbone's viewer)."
            ) from None
        config.feed = feed
        config.broker = args.backbone or args.broker
    host, port = listener.getsockname()[:2]
    scheme = "https" if args.tls_cert else "http"
    shown = f"[{host}]" if ":" in host else host
    where = [f"site {args.site}", "every plane" if plane is None else f"plane {plane}"]
    if feed is not None:
        where.append(f"live from {config.broker}" + (f" as {args.username}" if args.username
                                                     else ""))
    if args.db is not None:
        where.append(f"replay of {args.db}")
    if feed is None and args.db is None:
        where.append("no --broker nor --db: site map and calibration page only")
    url = f"{scheme}://{shown}:{port}/"
    if auth.run_token is not None:
        url += f"login?token={auth.run_token}"
        where.append("no --users: this link logs in as admin until the dashboard stops")
    else:
        where.append(f"users of {args.users}")
    if args.json:
        print(json.dumps({"url": url, "site": str(args.site), "plane": plane,
                          "planes": config.planes, "broker": config.broker or None,
                          "users": None if args.users is None else str(args.users),
                          "db": None if args.db is None else str(args.db)}), flush=True)
    else:
        print(f"dashboard on {url} ({', '.join(where)}); Ctrl-C stops it", flush=True)
    if not auth.loopback and not auth.secure:
        print("cblrs dashboard: warning: passwords and session cookies cross the network in "
              "clear; give --tls-cert and --tls-key, or serve it behind a TLS proxy (--origin "
              "https://...).", file=sys.stderr, flush=True)
    from cblrs.dashboard.connections import raise_open_files_limit, serve  # lazy, as above

    raise_open_files_limit()  # connections, not files, should run out first: see connections.py
    server = uvicorn.Server(server_config(create_app(config, auth), args.tls_cert,
                                          args.tls_key))
    previous = _stop_cleanly_on_sigterm(server)
    try:
        serve(server, [listener])  # a stalled TLS handshake ends within seconds
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if feed is not None:
            feed.close()
        listener.close()
    print("dashboard stopped", file=sys.stderr)
    return 0


def _stop_cleanly_on_sigterm(server: Any) -> Any:
    """Make SIGTERM a clean stop with exit code 0, as ``cblrs matcher``'s and ``cblrs
    camera``'s: uvicorn handles the SIGTERM (a graceful shutdown), then raises it again once
    it has shut down, and the default action would end the process by the signal (exit
    -15, reported by ``cblrs up`` as such) before the feed is closed. With this handler the
    raised-again signal only asks the server to stop (it has), and one that comes before
    uvicorn takes its signals over stops it as soon as it has started. Returns the handler
    it replaced (None: none replaced)."""
    if threading.current_thread() is not threading.main_thread():
        return None  # only the main thread sets handlers (uvicorn then leaves signals alone)

    def stop(signum: int, frame: Any) -> None:
        server.should_exit = True

    return signal.signal(signal.SIGTERM, stop)


def _shown_plane(args: argparse.Namespace, config: Any) -> int | None:
    """The plane shown from ``--plane`` (None: the overview of every plane)."""
    planes = config.planes
    text = (args.plane or "").strip()
    if text == "all" or (not text and len(planes) > 1):
        if args.db is not None:
            raise UsageError("--db replays one plane's matcher: give the plane too "
                             "(--plane ID).")
        if args.key is not None:
            raise UsageError("--key maps one pseudo plane: give the plane too (--plane ID).")
        return None
    if not text:
        return planes[0]
    if not text.isdecimal():
        raise UsageError(f"--plane {args.plane!r} must be a plane id or all.")
    plane = int(text)
    if config.site.planes is not None and plane not in planes:
        raise UsageError(f"--plane {plane} is not a plane of {args.site.name} "
                         f"(planes {planes}).")
    return plane


def _backbone(args: argparse.Namespace) -> None:
    """``--broker nats://...`` means ``--backbone nats://...``; mqtt:// an MQTT broker."""
    if args.broker is not None and args.broker.startswith("nats://"):
        if args.backbone is not None:
            raise UsageError("give the NATS servers once: --backbone or --broker nats://.")
        args.backbone, args.broker = args.broker, None
    elif args.broker is not None and args.broker.startswith("mqtt://"):
        args.broker = args.broker[len("mqtt://"):]
    if args.backbone is not None and not uses_nats(args):
        args.broker, args.backbone = args.backbone[len("mqtt://"):], None
    if args.site_id is not None and args.backbone is None:
        raise UsageError("--site-id names a site's NATS subjects: it goes with --backbone "
                         "nats://...")


def _authenticator(args: argparse.Namespace) -> Any:
    """Who may use the dashboard, from the options; refuses to serve beyond loopback without
    users (an open dashboard shows where people are to anyone who finds it)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.dashboard.auth import Authenticator
    from cblrs.dashboard.users import UsersError
    from cblrs.runtime.addresses import is_loopback_host

    loopback = is_loopback_host(args.host)
    if not loopback and args.users is None:
        raise UsageError(
            f"--host {args.host} serves beyond this machine, so it needs --users FILE (create "
            "it with cblrs dashboard-users add); without --users the dashboard serves on "
            "loopback only."
        )
    if (args.tls_cert is None) != (args.tls_key is None):
        raise UsageError("give --tls-cert and --tls-key together.")
    for option, path in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
        if path is not None and not path.is_file():
            raise InputError(f"{option} {path} does not exist.")
    if args.origin is not None and not re.fullmatch(r"https?://[^/?#\s]+/?", args.origin):
        raise UsageError(f"--origin {args.origin!r} must be a scheme and host, e.g. "
                         "https://dashboard.example.org.")
    check_positive(args.session_hours, "--session-hours")
    check_positive(args.idle_minutes, "--idle-minutes")
    try:
        return Authenticator(
            users_path=args.users,
            run_token=None if args.users is not None else secrets.token_urlsafe(24),
            session_s=args.session_hours * 3600.0,
            idle_s=args.idle_minutes * 60.0,
            secure=args.tls_cert is not None,
            origin=args.origin,
            loopback=loopback,
        )
    except UsersError as error:
        raise InputError(str(error)) from None


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
