"""The MQTT broker options and connection of the commands that talk to a broker
(``cblrs camera``, ``matcher``, ``linker``, ``dashboard``): address, login, TLS, client id."""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path
from typing import Any

from cblrs.cli.common import InputError, UsageError

logger = logging.getLogger(__name__)

PASSWORD_ENVIRONMENT = "CBLRS_MQTT_PASSWORD"


def add_mqtt_options(parser: argparse.ArgumentParser) -> None:
    """Broker address, login and TLS options shared by ``camera`` and ``matcher``."""
    group = parser.add_argument_group("broker")
    group.add_argument(
        "--broker",
        default="127.0.0.1:1883",
        metavar="HOST[:PORT]",
        help="MQTT broker (default 127.0.0.1:1883)",
    )
    group.add_argument("--username", help="MQTT user name (default: anonymous)")
    group.add_argument(
        "--password-file",
        type=Path,
        help=f"file holding the MQTT password (default: ${PASSWORD_ENVIRONMENT})",
    )
    group.add_argument("--ca-file", type=Path, help="CA certificate of the broker; enables TLS")
    group.add_argument("--cert-file", type=Path, help="client certificate (PEM) for TLS")
    group.add_argument("--key-file", type=Path, help="client certificate key (PEM) for TLS")
    group.add_argument(
        "--client-id",
        help="MQTT client id (cameras: cblrs-camera-PLANE-CAMERA; matchers: the user name or "
        "matcherPLANE); a restarted matcher resumes its session under the same id",
    )


def parse_broker(text: str) -> tuple[str, int]:
    """``HOST[:PORT]`` -> (host, port); one sentence for anything else."""
    host, separator, port_text = text.rpartition(":") if ":" in text else (text, "", "1883")
    if not host.strip():
        raise UsageError(f"--broker {text!r} names no host; write HOST or HOST:PORT.")
    if not (port_text.isascii() and port_text.isdigit()) or not 1 <= int(port_text) <= 65535:
        raise UsageError(
            f"--broker {text!r}: the port must be a number from 1 to 65535."
            if separator
            else f"--broker {text!r} must be HOST or HOST:PORT."
        )
    return host.strip(), int(port_text)


def mqtt_settings(args: argparse.Namespace) -> Any:
    """:class:`MqttSettings` from the broker options; the password never comes from argv."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.transport.mqtt_transport import MqttSettings

    host, port = parse_broker(args.broker)
    password = read_password(args)
    for name in ("ca_file", "cert_file", "key_file"):
        path = getattr(args, name)
        if path is not None and not path.is_file():
            raise InputError(f"--{name.replace('_', '-')} {path} does not exist.")
    return MqttSettings(
        host=host,
        port=port,
        username=args.username,
        password=password,
        ca_file=args.ca_file,
        cert_file=args.cert_file,
        key_file=args.key_file,
        protocol=getattr(args, "mqtt_version", "5"),
    )


def read_password(args: argparse.Namespace) -> str | None:
    """The password of ``--password-file`` (or the environment, with ``--username``)."""
    if args.password_file is not None:
        try:
            mode = args.password_file.stat().st_mode
            password = args.password_file.read_text().strip()
        except OSError as error:
            raise UsageError(
                f"cannot read --password-file {args.password_file}: {error}."
            ) from None
        if mode & 0o077:  # warned, not refused: the login works, the secret is exposed
            logger.warning(
                "--password-file %s is readable by other users of this machine (mode %04o); "
                "chmod 600 it", args.password_file, mode & 0o7777)
        return password
    if args.username is not None:
        return os.environ.get(PASSWORD_ENVIRONMENT)
    return None


def connect_or_queue(transport: Any, where: str = "in memory") -> None:
    """Connect; if the broker cannot be reached, say so at once and keep trying.

    A refused login is an error; an absent broker is not: messages wait (``where``) meanwhile.
    """
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.transport.protocol import TransportError

    try:
        transport.connect()
    except TransportError as error:
        if "refused the connection" in str(error):
            raise
        logger.warning(
            "%s Messages wait %s; reconnecting every %g s at most.",
            str(error).rstrip("."),
            where,
            getattr(transport.settings, "reconnect_max_s", 5.0),
        )
        transport.connect(wait=False)
