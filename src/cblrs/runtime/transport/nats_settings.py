"""How a client reaches the NATS backbone: servers, login, TLS, streams' and consumers' set-up.

:class:`NatsSettings` (and :class:`LeaseSettings`, a lease one client at a time holds) are plain
data, importable without the nats-py client: the CLI builds them from its options,
:mod:`~cblrs.runtime.broker.nats_auth` from a site's logins, and
:class:`~cblrs.runtime.transport.nats_transport.NatsTransport` connects with them;
:func:`attempt_reason` says in words why an attempt to connect failed.
"""

from __future__ import annotations

import math
import os
import ssl
from dataclasses import dataclass, field, replace
from typing import Any

from cblrs.runtime.transport.nats_subjects import validate_site
from cblrs.runtime.transport.protocol import TransportError


@dataclass(frozen=True)
class LeaseSettings:
    """A lease that one client at a time holds (e.g. a plane's matcher).

    Attributes:
        key: the key in the ``cblrs_leases`` bucket (letters, digits, ``-_``).
        ttl_s: how long the lease outlives its holder's last renewal; the bucket keeps the
            TTL it was created with.
        wait_s: how long :meth:`NatsTransport.connect` waits for a held lease to free up
            before refusing.
        what: what the lease guards, for messages (e.g. "plane 1").
    """

    key: str
    ttl_s: float = 10.0
    wait_s: float = 0.0
    what: str = ""


@dataclass(frozen=True)
class NatsSettings:
    """How to reach a NATS server or cluster and how the streams and consumer are set up.

    Attributes:
        servers: ``nats://host:port`` of one or more nodes (the client fails over).
        username: user name (None: none).
        password: password; from the environment or a 0600 file, never the repository.
        ca_file: CA certificate that signed the servers' (TLS; None: no TLS).
        cert_file: this client's certificate, when the servers require one.
        key_file: the certificate's private key.
        site: the site id every subject is prefixed with (``cblrs.<site>.<plane>...``), so
            several sites share one cluster; None: ``cblrs.<plane>...``.
        manage: create missing streams and the lease bucket (an administrator's right);
            None: when there is no username (a local server without users). Without it a
            missing stream or bucket is one sentence saying who creates it.
        connect_timeout_s: how long ``connect()`` waits for a server.
        reconnect_wait_s: delay between reconnection attempts.
        replicas: stream replicas; None: 3 on a cluster, else 1.
        retention_s: how long the streams keep messages (the replay horizon of a plane).
        duplicate_window_s: how long JetStream remembers message ids.
        ack_wait_s: redelivery of an un-acknowledged message after this long.
        max_ack_pending: deliveries awaiting acknowledgement, at most.
        pull_batch: messages asked for per pull request.
        heartbeat_s: idle heartbeat of pull requests (a silent consumer is asked again).
        publish_timeout_s: wait for a stream's acknowledgement before sending again.
        publish_window: stream publishes sent and awaiting acknowledgement at once; they
            leave in order on one connection, and what is not acknowledged is sent again in
            that order.
        max_camera_rate_hz: the highest message rate a camera's subject (its detections, or
            its status) has legitimately; with ``retention_s`` it sets
            :attr:`messages_per_camera`.
        max_msgs_per_camera: how many messages a plane's detections stream keeps per camera
            subject, at most; a publish beyond is refused (JetStream's discard-new per
            subject), so a camera that floods fills its own subject only. None:
            ``retention_s`` x ``max_camera_rate_hz``.
        max_msg_bytes: the largest message a plane's detections stream stores (the matcher
            accepts 256 KiB).
    """

    servers: tuple[str, ...] = ("nats://127.0.0.1:4222",)
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_file: str | os.PathLike | None = None
    cert_file: str | os.PathLike | None = None
    key_file: str | os.PathLike | None = None
    site: str | None = None
    manage: bool | None = None
    connect_timeout_s: float = 5.0
    reconnect_wait_s: float = 0.25
    replicas: int | None = None
    retention_s: float = 7 * 24 * 3600.0
    duplicate_window_s: float = 600.0
    ack_wait_s: float = 30.0
    max_ack_pending: int = 20_000
    pull_batch: int = 500
    heartbeat_s: float = 1.0
    publish_timeout_s: float = 2.0
    publish_window: int = 256
    max_camera_rate_hz: float = 30.0
    max_msgs_per_camera: int | None = None
    max_msg_bytes: int = 256 * 1024

    def __post_init__(self) -> None:
        if self.site is not None:
            validate_site(self.site)
        if self.publish_window < 1:
            raise ValueError(f"publish_window must be at least 1, got {self.publish_window}.")
        if self.max_msgs_per_camera is not None and self.max_msgs_per_camera < 1:
            raise ValueError("max_msgs_per_camera must be at least 1, got "
                             f"{self.max_msgs_per_camera}.")

    @property
    def messages_per_camera(self) -> int:
        """How many messages a detections stream keeps per camera subject (see
        ``max_msgs_per_camera``)."""
        if self.max_msgs_per_camera is not None:
            return self.max_msgs_per_camera
        return max(1, math.ceil(self.retention_s * self.max_camera_rate_hz))

    @property
    def manages(self) -> bool:
        """Whether this client creates missing streams and buckets (see ``manage``)."""
        return self.username is None if self.manage is None else self.manage

    @property
    def inbox_prefix(self) -> str:
        """Where answers to this client go: ``_INBOX.<user>`` with a username (its
        permissions let only it read there), else ``_INBOX``."""
        if self.username is None:
            return "_INBOX"
        return f"_INBOX.{self.username.replace('.', '//')}"

    def tls_context(self) -> ssl.SSLContext | None:
        """The TLS context of ``ca_file``/``cert_file``/``key_file`` (None without TLS).

        Raises:
            TransportError: a file is missing or unreadable.
        """
        if self.ca_file is None:
            return None
        try:
            context = ssl.create_default_context(cafile=str(self.ca_file))
            if self.cert_file is not None:
                context.load_cert_chain(str(self.cert_file),
                                        None if self.key_file is None else str(self.key_file))
        except (OSError, ssl.SSLError) as error:
            raise TransportError(f"cannot use the TLS files for NATS: {error}.") from None
        return context

    @classmethod
    def from_url(cls, url: str, **options: Any) -> NatsSettings:
        """Settings from ``nats://host:port[,host:port...]`` (also ``nats://a,nats://b``).

        Raises:
            ValueError: not a nats:// address.
        """
        text = url.strip()
        if not text.startswith("nats://"):
            raise ValueError(f"{url!r} is not a nats:// address (nats://host:port[,host:port]).")
        servers = []
        for part in text[len("nats://"):].split(","):
            part = part.strip().removeprefix("nats://")
            if not part:
                continue
            host, _, port = part.rpartition(":") if ":" in part else (part, "", "4222")
            if not port.isdigit():
                raise ValueError(f"{url!r}: {part!r} is not host:port.")
            servers.append(f"nats://{host or '127.0.0.1'}:{port}")
        if not servers:
            raise ValueError(f"{url!r} names no server.")
        return cls(servers=tuple(servers), **options)


def with_servers(settings: NatsSettings, url: str) -> NatsSettings:
    """``settings`` pointed at the servers of ``url`` (``nats://host:port[,...]``)."""
    return replace(settings, servers=NatsSettings.from_url(url).servers)


def _is_login_refusal(error: BaseException) -> bool:
    return "authorization" in str(error).lower()


def _is_tls_failure(error: BaseException) -> bool:
    lowered = str(error).lower()
    return isinstance(error, ssl.SSLError) or "tls" in lowered or "ssl" in lowered \
        or "certificate" in lowered


def attempt_reason(error: BaseException, settings: NatsSettings) -> str:
    """Why an attempt to connect failed, in words: the operating system's for a refused or
    unreachable port, a TLS failure with what to check, a silent port, a refused login."""
    text = str(error) or type(error).__name__
    if _is_login_refusal(error):
        return (f"the servers refused the login {settings.username or '(none)'} (wrong or "
                "missing user name and password)")
    if _is_tls_failure(error):
        return (f"TLS failed ({text}); the servers require TLS with a client certificate "
                "signed by their CA (--ca-file, --cert-file, --key-file)")
    if isinstance(error, TimeoutError):
        return (f"no NATS greeting within {round(settings.connect_timeout_s):g} s (the TCP "
                "connection opens, or did, but what answers is not a NATS server"
                + ("" if settings.ca_file is not None else ", or it wants TLS first")
                + ")")
    if isinstance(error, OSError) and error.errno is not None:
        reason = os.strerror(error.errno)
        if settings.ca_file is not None and settings.cert_file is None \
                and isinstance(error, (BrokenPipeError, ConnectionResetError)):
            # The server ended the TLS handshake: nats-py sees only the closed connection.
            reason += (" (the server closed the TLS connection: it may require a client "
                       "certificate, --cert-file and --key-file)")
        return reason
    return text
