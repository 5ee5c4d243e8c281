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
        "--matchers", default="matcher1", metavar="ID,ID,...", help="matcher ids (default matcher1)"
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


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs broker-config`` with its parsed arguments; the exit code."""
    cameras = _names(args.cameras, "--cameras")
    matchers = _names(args.matchers, "--matchers")
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
        queue_bytes=int(args.queue_mb * 2**20),
        autosave_s=args.autosave,
        run_as=args.run_as,
        ca_directory=args.ca_dir,
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
        if files.tls:
            cert, key = files.client_certificates[user]
            options += ["--ca-file", str(files.ca_file), "--cert-file", str(cert)]
            options += ["--key-file", str(key)]
        return " ".join(shlex.quote(option) for option in options)

    lines = [
        f"Wrote a Mosquitto configuration to {files.directory}",
        f"  config        {files.config}",
        f"  passwords     {files.password_file} (hashed)",
        f"  acl           {files.acl_file}",
        f"  credentials   {files.credentials_file} (mode 0600, clear text: keep it private)",
        f"  per user      {files.directory / 'secrets'}/<user>.password (mode 0600)",
    ]
    if files.persistence_directory is not None:
        lines.append(f"  persistence   {files.persistence_directory}")
    if files.tls and files.ca_file is not None:
        lines.append(
            f"  TLS           {files.ca_file.parent} (CA, server and client certificates, "
            "valid 365 days)"
        )
        lines.append(f"  CA key        {files.ca_key_file} (keep it offline; not needed to run)")
    lines.append(
        f"  limits        {args.queue_mb:g} MiB queued per client, packets up to 1 MiB, "
        f"saved every {args.autosave} s"
        + (f"; runs as user {files.run_as}" if files.run_as else "")
    )
    lines += [
        "",
        "Start the broker:",
        f"  mosquitto -c {shlex.quote(str(files.config))}",
        "",
        "Before the cameras, create the matcher's session so the broker keeps its messages:",
        f"  cblrs matcher --prepare --references REFS --db DB "
        f"{client_options(matchers[0]) if matchers else ''}".rstrip(),
        "",
        "Users: " + ", ".join(f"{user} ({role})" for user, role in files.roles.items()),
        "Connect a camera / matcher with (copy only that user's files to its machine):",
        f"  cblrs camera ... --camera {cameras[0]} {client_options(cameras[0])}",
    ]
    if matchers:
        lines.append(f"  cblrs matcher ... {client_options(matchers[0])}")
    print("\n".join(lines))
    return 0
