"""How an MQTT transport reaches its broker: :class:`MqttSettings` (address, login, TLS,
timeouts, limits) and the TCP socket's options (no self-connection, no Nagle), and
:func:`unreachable_reason` for a broker that does not answer.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class MqttSettings:
    """How to reach and log into a broker.

    Attributes:
        host: broker address.
        port: broker port (1883 plain, 8883 usual for TLS).
        username: user name (None: anonymous).
        password: password; pass it from the environment or a 0600 file, never the repo.
        ca_file: CA certificate that signed the broker's certificate; enables TLS.
        cert_file: client certificate (PEM), when the broker requires one.
        key_file: the client certificate's private key (PEM).
        keepalive_s: MQTT keepalive, seconds.
        session_expiry_s: how long the broker keeps a disconnected persistent session.
        reconnect_min_s: first reconnection delay; doubles up to ``reconnect_max_s``.
        reconnect_max_s: longest reconnection delay.
        connect_timeout_s: how long ``connect()`` waits for the broker's answer.
        max_inflight: QoS 1 publishes sent but not yet acknowledged, at most (paho's window).
        max_handed: publishes handed to paho and not yet acknowledged, at most; the rest
            wait in the transport's own queue (paho numbers messages with 16 bits and fails
            past 65 535 outstanding ones).
        tcp_nodelay: disable Nagle's algorithm on the connection, so small packets (a
            track update, an acknowledgement) leave at once instead of up to ~40 ms later.
        protocol: MQTT version: "5", "3.1.1" (e.g. the NATS server's MQTT listener, which
            refuses MQTT 5), or "auto" (MQTT 5, and 3.1.1 when the broker refuses version 5).
            Under 3.1.1 the session expiry is the broker's, overlapping subscriptions get no
            identifiers, ``close(unclean=True)`` does not make the broker send the will, and
            a publish's answer is always "accepted" (3.1.1 has no reason codes).
    """

    host: str = "127.0.0.1"
    port: int = 1883
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    keepalive_s: int = 30
    session_expiry_s: int = 24 * 3600
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    connect_timeout_s: float = 5.0
    max_inflight: int = 100
    max_handed: int = 1000
    tcp_nodelay: bool = True
    protocol: str = "5"

    @property
    def mqtt5(self) -> bool:
        """Whether MQTT 5 is spoken (else 3.1.1)."""
        return self.protocol != "3.1.1"

    @property
    def tls(self) -> bool:
        """Whether the connection uses TLS."""
        return self.ca_file is not None

    @property
    def address(self) -> str:
        """``host:port`` of the broker, for messages."""
        return f"{self.host}:{self.port}"


def _refuse_self_connection(client, userdata, sock) -> None:
    """paho's on_socket_open: refuse a TCP connection to itself.

    Reconnecting to a local broker that is down, a client can draw the broker's own port as
    its source port and connect to itself (TCP simultaneous open); it would then hold the
    port the broker needs to start again. The OSError makes paho retry later.
    """
    try:
        same = sock.getsockname() == sock.getpeername()
    except (OSError, AttributeError):
        return
    if same:
        sock.close()
        raise OSError(errno.ECONNREFUSED, "connected to itself: nothing listens on that port")


def _socket_options(client, userdata, sock) -> None:
    """paho's on_socket_open: refuse a self-connection, disable Nagle's algorithm (paho
    does not set TCP_NODELAY)."""
    _refuse_self_connection(client, userdata, sock)
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except (OSError, AttributeError):  # not a TCP socket (e.g. a unix socket): nothing to do
        pass


def unreachable_reason(host: str, port: int, timeout: float = 2.0) -> str | None:
    """Why a TCP connection to ``host:port`` fails (the OS's words), or None if it opens."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except TimeoutError:
        return f"no TCP answer within {timeout:g} s"
    except OSError as error:
        return error.strerror or str(error)
