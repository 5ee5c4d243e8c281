"""Backbone options shared by ``cblrs camera`` and ``cblrs matcher``: MQTT (default) or NATS.

``--backbone nats://host:port[,host:port...]`` switches a camera or a matcher from MQTT to
NATS JetStream (:mod:`cblrs.runtime.transport.nats_transport`); cameras may also stay on MQTT and
publish to the NATS server's MQTT listener (``--broker HOST:MQTTPORT``; the default
``--mqtt-version auto`` falls back to 3.1.1, the version NATS speaks). The login and TLS
options (``--username``, ``--password-file``, ``--ca-file``, ``--cert-file``, ``--key-file``)
serve both backbones; ``--site-id`` prefixes every NATS subject so several sites share one
cluster.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from cblrs.cli.common import UsageError


def add_backbone_options(parser: argparse.ArgumentParser, matcher: bool) -> None:
    """Add ``--backbone URL`` and the NATS options (the matcher's too when ``matcher``)."""
    group = parser.add_argument_group("NATS backbone (instead of MQTT)")
    group.add_argument(
        "--backbone",
        metavar="URL",
        help="nats://host:port[,host:port...]: use NATS JetStream (give every node of a "
        "cluster); default: MQTT at --broker",
    )
    group.add_argument(
        "--site-id",
        metavar="ID",
        help="NATS: the site's id, a prefix of every subject (cblrs.ID.PLANE...) so several "
        "sites share one cluster; plane ids are then unique per site (default: none)",
    )
    if not matcher:
        return
    group.add_argument(
        "--lease-ttl",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="NATS: the plane lease outlives a dead matcher by this long (default 10; set "
        "when the lease bucket is created, by --prepare with the admin's login)",
    )
    group.add_argument(
        "--lease-wait",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="NATS: wait this long for another matcher's lease on the plane to expire "
        "(default 0: refuse at once)",
    )
    group.add_argument(
        "--replicas",
        type=int,
        choices=(1, 3, 5),
        help="NATS: stream replicas when creating the streams (default 3 on a cluster, else 1)",
    )
    group.add_argument(
        "--retention-hours",
        type=float,
        default=168.0,
        help="NATS: how long the stream keeps detections (the replay horizon; default 168)",
    )
    group.add_argument(
        "--max-msgs-per-camera",
        type=int,
        metavar="N",
        help="NATS, with --prepare: messages the plane's stream keeps per camera subject; "
        "beyond, a camera's publishes are refused until retention makes room (default: "
        "--retention-hours x 30 a second; docs/security.md, 'Stream limits')",
    )


logger = logging.getLogger(__name__)


def uses_nats(args: argparse.Namespace) -> bool:
    """Whether ``--backbone`` names NATS; UsageError for a URL that is neither nats:// nor
    mqtt://."""
    backbone = getattr(args, "backbone", None)
    if backbone is None or backbone.startswith("mqtt://"):
        return False
    if not backbone.startswith("nats://"):
        raise UsageError(f"--backbone {backbone!r} must be nats://host:port[,host:port...].")
    return True


def nats_settings(args: argparse.Namespace, **options: Any) -> Any:
    """:class:`NatsSettings` from ``--backbone``, the login options and ``options``."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.cli.mqtt_options import read_password
    from cblrs.runtime.transport.nats_settings import NatsSettings
    from cblrs.runtime.transport.protocol import TransportError

    try:
        return NatsSettings.from_url(
            args.backbone, username=args.username, password=read_password(args),
            ca_file=args.ca_file, cert_file=args.cert_file, key_file=args.key_file,
            site=args.site_id, **options
        )
    except ValueError as error:
        raise UsageError(f"--backbone: {error}") from None
    except TransportError as error:
        raise UsageError(f"--site-id: {error}") from None


def matcher_transport(
    args: argparse.Namespace,
    matcher_id: str,
    plane_id: int,
    *,
    rebuild: bool,
    will: Any,
    on_failure: Any,
) -> Any:
    """The matcher's NATS transport: the plane's durable consumer and lease.

    Args:
        rebuild: the store is empty, so the consumer replays the plane's stream from the
            start (the store is rebuilt from the stream).
    """
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.transport.nats_settings import LeaseSettings
    from cblrs.runtime.transport.nats_subjects import lease_key
    from cblrs.runtime.transport.nats_transport import NatsTransport

    if args.lease_ttl <= 0 or args.lease_wait < 0 or args.retention_hours <= 0:
        raise UsageError("--lease-ttl and --retention-hours must be > 0, --lease-wait >= 0.")
    if args.max_msgs_per_camera is not None and args.max_msgs_per_camera < 1:
        raise UsageError("--max-msgs-per-camera must be at least 1.")
    # --prepare (with the admin's login) creates the plane's streams, consumer and the
    # lease bucket; a matcher's own login may not (see docs/security.md).
    settings = nats_settings(
        args, replicas=args.replicas, retention_s=args.retention_hours * 3600.0,
        manage=True if args.prepare else None, max_msgs_per_camera=args.max_msgs_per_camera,
    )
    where = f"plane {plane_id}" + (f" of site {args.site_id}" if args.site_id else "")
    return NatsTransport(
        matcher_id,
        settings,
        durable=f"cblrs-plane-{plane_id}",
        replay=rebuild,
        lease=LeaseSettings(lease_key(plane_id, args.site_id), args.lease_ttl, args.lease_wait,
                            where),
        will=will,
        on_failure=on_failure,
    )


def camera_transport(args: argparse.Namespace, client_id: str) -> Any:
    """A camera's NATS transport: JetStream publishes in order, a window of them awaiting the
    stream's acknowledgement at once."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.transport.nats_transport import NatsTransport

    return NatsTransport(client_id, nats_settings(args))


def connect_or_spool(transport: Any, where: str) -> None:
    """Start a camera's NATS connection in the background; if it is not up within a few
    seconds, say why (refused, no answer, TLS) at once and go on: messages wait ``where``
    and are sent, in order, once a server answers (as :func:`~cblrs.cli.mqtt_options.
    connect_or_queue` does on MQTT).

    Raises:
        TransportError: the servers refused the login (an error, as MQTT's refusal is).
    """
    settings = transport.settings
    logger.info("%s: connecting to the NATS servers at %s", transport.client_id,
                ", ".join(settings.servers))
    transport.connect(wait=False)
    problem = transport.wait_connected(settings.connect_timeout_s + 1.0)
    if problem is not None:
        logger.warning("%s. Messages wait %s; connecting again every %g s in the background.",
                       problem.rstrip("."), where, settings.reconnect_wait_s)
