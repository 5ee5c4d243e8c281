"""``cblrs broker-config``: a Mosquitto configuration with users, ACL and optional TLS, or
(``--backbone nats``) a NATS server or cluster with users, permissions and TLS."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from cblrs.cli.common import UsageError, add_output_options, print_json
from cblrs.runtime.broker.mosquitto_config import (
    DEFAULT_AUTOSAVE_S,
    DEFAULT_QUEUE_BYTES,
    write_broker_config,
)


def register(subparsers) -> None:
    """Add the ``cblrs broker-config`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "broker-config",
        help="write a Mosquitto or NATS configuration (users, permissions, TLS) for cameras, "
        "matchers and viewers",
        description=(
            "Write mosquitto.conf, a hashed password file and an ACL (or, with --backbone nats, "
            "one nats-server configuration per node with users and permissions), and each "
            "client's credentials into a folder of its own. A camera may publish only its own "
            "topics; a matcher reads the detections of its planes and publishes their tracks; "
            "read-only viewers see tracks; on NATS an admin login alone manages streams. No "
            "anonymous access. See docs/security.md."
        ),
    )
    parser.add_argument(
        "--backbone", choices=("mosquitto", "nats"), default="mosquitto",
        help="which broker to configure (default mosquitto)",
    )
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument(
        "--cameras", required=True, metavar="ID,ID,...", help="camera ids, comma-separated"
    )
    parser.add_argument(
        "--matchers", default="matcher1", metavar="ID[=PLANE+PLANE],...",
        help="matcher ids (default matcher1), each serving every plane of --planes, or "
        "ID=PLANES for the planes it alone may serve, e.g. m1=1,m2=2+3",
    )
    parser.add_argument(
        "--planes",
        default="1",
        metavar="ID,ID,...",
        help="plane ids the matchers serve (default 1)",
    )
    parser.add_argument("--port", type=int, help="listener port (default 1883, or 8883 with --tls)")
    parser.add_argument(
        "--bind", default="127.0.0.1", help="listener address (0.0.0.0 for other machines)"
    )
    parser.add_argument(
        "--tls",
        action="store_true",
        help="TLS-only listener; generates a CA, a server and one client certificate per user",
    )
    parser.add_argument(
        "--allow-plaintext", action="store_true",
        help="accept a listener beyond loopback without TLS (passwords and messages cross the "
        "network in clear): only on a network already encrypted and trusted, e.g. a VPN",
    )
    parser.add_argument(
        "--no-persistence",
        action="store_true",
        help="do not keep queued messages across broker restarts",
    )
    parser.add_argument("--no-viewer", action="store_true", help="no read-only viewer user")
    parser.add_argument(
        "--viewers", metavar="ID,ID,...",
        help="read-only logins, one per dashboard (default: viewer); a login is one client "
        "at a time",
    )
    parser.add_argument(
        "--linkers", metavar="ID,ID,...",
        help="logins of cblrs linker (default: none): each reads every plane's tracks and "
        "publishes the site's global tracks, events and live summary (plane 0)",
    )
    parser.add_argument(
        "--clients-dir", type=Path,
        help="folder of the per-client folders of secrets (default: OUT-clients, beside OUT, "
        "never inside it); copy each client's folder to that client only",
    )
    parser.add_argument(
        "--queue-mb", type=float, default=DEFAULT_QUEUE_BYTES / 2**20,
        help="bytes of queued messages the broker holds per client, MiB (default 64; beyond "
        "it the broker drops messages and the cameras' spools send them again)",
    )
    parser.add_argument(
        "--autosave", type=int, default=DEFAULT_AUTOSAVE_S, metavar="SECONDS",
        help="save the broker's database every N seconds (default 1)",
    )
    parser.add_argument(
        "--run-as", metavar="USER",
        help="user Mosquitto runs as when started as root (default: mosquitto; the files it "
        "reads are handed to that user). Never root in production.",
    )
    parser.add_argument(
        "--ca-dir", type=Path,
        help="with --tls: folder for the CA's private key (default: OUT-ca, beside OUT, "
        "never inside it)",
    )
    parser.add_argument(
        "--force", action="store_true", help="overwrite an existing configuration (new passwords)"
    )
    nats = parser.add_argument_group("NATS (--backbone nats)")
    nats.add_argument(
        "--nodes", default="127.0.0.1", metavar="HOST,HOST,...",
        help="one address per node (several make a cluster; default 127.0.0.1)",
    )
    nats.add_argument("--site-id", metavar="ID", help="the site's subject prefix (cblrs.ID...)")
    nats.add_argument("--admin", default="admin", help="the admin's login (default admin)")
    nats.add_argument("--no-tls", action="store_true",
                      help="NATS without TLS (default: TLS with client certificates)")
    nats.add_argument("--no-mqtt", action="store_true", help="no MQTT listener on the nodes")
    nats.add_argument("--mqtt-port", type=int, default=1883, help="MQTT listener (default 1883)")
    nats.add_argument("--cluster-port", type=int, default=6222, help="routes (default 6222)")
    nats.add_argument("--monitor-port", type=int, default=8222,
                      help="monitoring pages, on loopback only (default 8222)")
    add_output_options(parser)
    parser.set_defaults(handler=run)


def _names(text: str, option: str) -> list[str]:
    names = [name.strip() for name in text.split(",") if name.strip()]
    if len(names) != len(set(names)):
        raise UsageError(f"{option} lists a name twice: {text!r}.")
    return names


def _planes(text: str) -> list[int]:
    try:
        return [int(value) for value in text.split(",") if value.strip()]
    except ValueError:
        raise UsageError(f"--planes {text!r} must be integers, e.g. 1 or 1,2.") from None


def parse_matchers(text: str) -> list[str] | dict[str, list[int]]:
    """``m1,m2`` (every plane of --planes) or ``m1=1,m2=2+3`` (the planes of each)."""
    entries = _names(text, "--matchers")
    if not any("=" in entry for entry in entries):
        return entries
    planes: dict[str, list[int]] = {}
    for entry in entries:
        name, _, served = entry.partition("=")
        try:
            planes[name.strip()] = [int(plane) for plane in served.split("+")]
        except ValueError:
            raise UsageError(
                f"--matchers: {entry!r} must be ID=PLANE[+PLANE...], e.g. matcher1=1+2."
            ) from None
    if len(planes) != len(entries):
        raise UsageError(f"--matchers lists a name twice: {text!r}.")
    return planes


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs broker-config`` with its parsed arguments; the exit code."""
    cameras = _names(args.cameras, "--cameras")
    matchers = parse_matchers(args.matchers)
    if not cameras:
        raise UsageError("--cameras needs at least one camera id.")
    planes = _planes(args.planes)
    if args.backbone == "nats":
        return _run_nats(args, cameras, matchers, planes)
    port = args.port if args.port is not None else (8883 if args.tls else 1883)
    if not (args.queue_mb > 0 and args.queue_mb < float("inf")):
        raise UsageError(f"--queue-mb must be a positive number, got {args.queue_mb}.")
    if (args.out / "mosquitto.conf").exists() and not args.force:
        raise UsageError(
            f"{args.out / 'mosquitto.conf'} exists; use --force to overwrite it "
            "(this generates new passwords)."
        )
    files = write_broker_config(
        args.out,
        cameras,
        matchers,
        port=port,
        plane_ids=planes,
        tls=args.tls,
        persistence=not args.no_persistence,
        bind=args.bind,
        viewer=not args.no_viewer,
        viewers=_names(args.viewers, "--viewers") if args.viewers else None,
        linkers=_names(args.linkers, "--linkers") if args.linkers else (),
        queue_bytes=int(args.queue_mb * 2**20),
        autosave_s=args.autosave,
        run_as=args.run_as,
        ca_directory=args.ca_dir,
        clients_directory=args.clients_dir,
        allow_plaintext=args.allow_plaintext,
    )
    if args.json:
        print_json({**files.to_dict(), "start": ["mosquitto", "-c", str(files.config)]})
        return 0
    host = "127.0.0.1" if files.bind in ("0.0.0.0", "::") else files.bind

    def client_options(user: str) -> str:
        options = [
            "--broker",
            f"{host}:{files.port}",
            "--username",
            user,
            "--password-file",
            str(files.password_files[user]),
        ]
        client = files.clients[user]
        if files.tls:
            options += ["--ca-file", str(client.ca_file), "--cert-file", str(client.cert_file)]
            options += ["--key-file", str(client.key_file)]
        return " ".join(shlex.quote(option) for option in options)

    lines = [
        f"Wrote a Mosquitto configuration to {files.directory}",
        f"  config        {files.config}",
        f"  passwords     {files.password_file} (hashed)",
        f"  acl           {files.acl_file}",
        f"  clients       {files.clients_directory}/<user>/ (its password"
        + (", certificate and key" if files.tls else "") + "; 0700): copy each folder to "
        "that client only, then delete it here",
    ]
    if files.persistence_directory is not None:
        lines.append(f"  persistence   {files.persistence_directory}")
    if files.tls and files.ca_file is not None:
        lines.append(
            f"  TLS           {files.ca_file.parent} (CA and server certificates, valid 365 "
            "days; client certificates are in the clients' folders)"
        )
        lines.append(f"  CA key        {files.ca_key_file} (keep it offline; not needed to run)")
    lines.append(
        f"  limits        {args.queue_mb:g} MiB queued per client, packets up to 1 MiB, "
        f"saved every {args.autosave} s"
        + (f"; runs as user {files.run_as}" if files.run_as else "")
    )
    matcher_names = [user for user, role in files.roles.items() if role == "matcher"]
    viewer_names = [user for user, role in files.roles.items() if role == "viewer"]
    lines += [
        "",
        "Logins: each login is one client at a time (the broker uses it as the client id): "
        "a second client with the same login takes over the first one's session (both log "
        "it and count it). Never share a login; give each dashboard its own viewer login "
        "(--viewers).",
        "",
        "Start the broker:",
        f"  mosquitto -c {shlex.quote(str(files.config))}",
        "",
        "Before the cameras, create the matcher's session so the broker keeps its messages:",
        f"  cblrs matcher --prepare --references REFS --db DB "
        f"{client_options(matcher_names[0]) if matcher_names else ''}".rstrip(),
        "",
        "Users: " + ", ".join(f"{user} ({role})" for user, role in files.roles.items()),
        "Connect a camera / matcher with (copy only that user's files to its machine):",
        f"  cblrs camera ... --camera {cameras[0]} {client_options(cameras[0])}",
    ]
    if matcher_names:
        lines.append(f"  cblrs matcher ... {client_options(matcher_names[0])}")
    if viewer_names:
        lines.append(f"  cblrs dashboard ... {client_options(viewer_names[0])}")
    print("\n".join(lines))
    return 0


def _run_nats(args: argparse.Namespace, cameras: list[str],
              matchers: list[str] | dict[str, list[int]], planes: list[int]) -> int:
    """``cblrs broker-config --backbone nats``: the nodes' configurations and credentials."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.broker.mosquitto_config import matcher_planes
    from cblrs.runtime.broker.nats_server import write_nats_backbone

    hosts = _names(args.nodes, "--nodes")
    if (args.out / "n1" / "n1.conf").exists() and not args.force:
        raise UsageError(f"{args.out / 'n1' / 'n1.conf'} exists; use --force to overwrite it "
                         "(this generates new passwords).")
    files = write_nats_backbone(
        args.out, cameras, matcher_planes(matchers, planes), hosts=hosts,
        port=args.port or 4222, cluster_port=args.cluster_port,
        monitor_port=args.monitor_port,
        mqtt_port=None if args.no_mqtt else args.mqtt_port, site=args.site_id,
        viewers=_names(args.viewers, "--viewers") if args.viewers else
        ([] if args.no_viewer else ["viewer"]),
        linkers=_names(args.linkers, "--linkers") if args.linkers else (),
        admin=args.admin, tls=not args.no_tls, ca_directory=args.ca_dir,
        clients_directory=args.clients_dir, allow_plaintext=args.allow_plaintext,
    )
    security = files.security
    if args.json:
        print_json({**files.to_dict(), "start": [["nats-server", "-c", str(node.config_path)]
                                                 for node in files.nodes]})
        return 0

    def client_options(user: str) -> str:
        client = security.clients[user]
        options = ["--backbone", files.url, "--username", user,
                   "--password-file", str(client.password_file)]
        if security.site:
            options += ["--site-id", security.site]
        if security.tls:
            options += ["--ca-file", str(client.ca_file), "--cert-file", str(client.cert_file),
                        "--key-file", str(client.key_file)]
        return " ".join(shlex.quote(option) for option in options)

    roles = security.roles
    first = {role: next((user for user, kind in roles.items() if kind == role), None)
             for role in ("camera", "matcher", "viewer", "admin")}
    matcher = first["matcher"]
    served = matcher_planes(matchers, planes).get(matcher, planes) if matcher else planes
    lines = [
        f"Wrote a NATS backbone ({len(files.nodes)} node{'s' if len(files.nodes) > 1 else ''}"
        f"{', TLS' if security.tls else ''}{', site ' + security.site if security.site else ''}"
        f") to {security.directory}",
        *(f"  {node.name:<12}  {node.config_path}" for node in files.nodes),
        "  users         bcrypt hashes inside each node's configuration (mode 0600)",
        f"  clients       {security.clients_directory}/<user>/ (password"
        + (", certificate and key" if security.tls else "") + "; 0700): copy each folder to "
        "that client only, then delete it here",
    ]
    if security.tls:
        lines.append(f"  CA keys       {security.ca_key_directory} (keep them offline; not "
                     "needed to run)")
    lines += [
        "",
        "Logins: on NATS a login may be shared by several clients (a viewer's by several "
        "dashboards); a matcher's login serves its planes one matcher at a time (the plane "
        "lease refuses a second).",
        "",
        "Start every node:",
        *(f"  nats-server -c {shlex.quote(str(node.config_path))}" for node in files.nodes),
        "",
        "Then, as the admin, create each plane's streams, consumer and the lease bucket "
        "(runtime logins may not):",
        f"  cblrs matcher --prepare --references REFS --db DB --client-id {matcher or 'matcher1'}"
        f" {client_options(args.admin)}",
        "",
        "Users: " + ", ".join(f"{user} ({role})" for user, role in roles.items()),
        "Connect (copy only that user's folder to its machine):",
        f"  cblrs camera ... --camera {cameras[0]} {client_options(cameras[0])}",
    ]
    if matcher is not None:
        lines.append(f"  cblrs matcher ... {client_options(matcher)}   (planes "
                     f"{', '.join(map(str, served))})")
    print("\n".join(lines))
    return 0
