"""``cblrs broker-config``: a Mosquitto configuration with users, ACL and optional TLS."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from cblrs.cli.common import UsageError, add_output_options, print_json
from cblrs.runtime.broker import DEFAULT_AUTOSAVE_S, DEFAULT_QUEUE_BYTES, write_broker_config


def register(subparsers) -> None:
    """Add the ``cblrs broker-config`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "broker-config",
        help="write a Mosquitto configuration (users, ACL, optional TLS) for cameras and matchers",
        description=(
            "Write mosquitto.conf, a hashed password file, an ACL and generated credentials for "
            "a set of cameras and matchers. A camera may publish only its own topics and read "
            "nothing; matchers read the detections of their planes and publish tracks; an "
            "optional read-only 'viewer' user sees tracks. No anonymous access."
        ),
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
        queue_bytes=int(args.queue_mb * 2**20),
        autosave_s=args.autosave,
        run_as=args.run_as,
        ca_directory=args.ca_dir,
        clients_directory=args.clients_dir,
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
