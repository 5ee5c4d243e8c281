"""Mosquitto configuration for the runtime: users, ACL, TLS, persistence; and a process wrapper.

:func:`write_broker_config` writes everything a broker needs into one directory::

    mosquitto.conf     listener, allow_anonymous false, password_file, acl_file, persistence,
                       queue and message limits
    passwords          PBKDF2-SHA512 hashes in Mosquitto's ``$7$`` format, computed here (no
                       clear password on any command line)
    acl                a camera publishes only its own detections and status and reads only
                       its confirmations and the matchers' status; matchers read detections,
                       publish tracks, analytics events, live summaries and confirmations and
                       hold their plane's lease; the viewer (the dashboard) reads tracks,
                       events, live summaries and status, and writes nothing
    credentials.json   the generated passwords (mode 0600)
    secrets/<user>.password   one user's password (mode 0600): copy it to that client only
    data/              persistence (queued QoS 1 messages survive a broker restart)
    tls/               the CA certificate, the server's certificate and key, client
                       certificates (with ``tls=True``); the CA's private key goes to a
                       separate folder (``<out>-ca/`` by default), never the broker's

Policies (the broker is a short buffer; each camera's disk spool is the long one, see
:mod:`cblrs.runtime.spool`):

* **queue**: no limit on the number of queued messages per client, a limit on their bytes
  (``queue_bytes``, default 64 MiB: about 149 000 messages of 450 bytes, 12 minutes of 20
  cameras at 10 fps). Mosquitto drops messages for a client whose queue is full *after*
  acknowledging them to the publisher, so nothing relies on that queue alone: a camera keeps
  every message until the matcher confirms it stored it, and sends again what the matcher
  does not confirm.
* **persistence**: the in-memory database is written on a clean stop and whenever more than
  ``autosave_s`` whole seconds (default 1) have passed since the last save — Mosquitto counts
  in whole seconds, so with the default it saves every one to two seconds, each save logged
  ("Saving in-memory database" as it begins; it writes a new file and renames it over the
  old one). A QoS 1 acknowledgement thus precedes durability: a ``kill -9`` of the broker
  loses what it acknowledged since the start of its last completed save (the last two to
  four seconds); the cameras still hold those messages (until the matcher confirms them)
  and send them again. A camera that does not wait for confirmations (``--confirm-timeout
  0``) only knows the broker acknowledged: its messages are on the broker's disk once a save
  begun after its last acknowledgement has completed. Saving after
  every change (``autosave_on_changes``) would close that second but rewrites the whole
  database each time: measured here, publishing fell from ~21 000 to 432 messages/s with
  2 000 messages queued and to 94/s with 8 000 (it would stall a plane whose matcher is
  down); saving every second cost nothing measurable with 100 000 queued (21 000/s).
* **message size**: ``max_packet_size`` 1 MiB (a camera's largest message is ~130 KB, the
  matcher accepts 256 KiB); bigger packets are refused, so nobody can fill the broker's
  memory with huge messages.
* **never root**: generated as root, the configuration runs Mosquitto as the ``mosquitto``
  user (``run_as``) and hands it the files it must read; tests that keep the files in a
  private temporary folder pass ``run_as="root"``.
* **TLS**: the client certificate's common name is the user name
  (``use_identity_as_username``): a client cannot present one camera's certificate and
  another's login.

:class:`~cblrs.runtime.mosquitto.MosquittoProcess` (in :mod:`cblrs.runtime.mosquitto`, and
importable from here) runs ``mosquitto -c mosquitto.conf`` as a child process.

It stays one module because the configuration, the ACL, the password file and the certificates
are one generated folder whose files name each other; running Mosquitto is in
:mod:`cblrs.runtime.mosquitto`.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
import json
import logging
import os
import pwd
import secrets
import stat
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cblrs.runtime.mosquitto import BrokerError, MosquittoProcess, find_mosquitto, free_port
from cblrs.runtime.mqtt_transport import MqttSettings
from cblrs.runtime.topics import ROOT, validate_client_id

logger = logging.getLogger(__name__)

__all__ = [
    "BrokerError",
    "BrokerFiles",
    "MosquittoProcess",
    "find_mosquitto",
    "free_port",
    "hash_password",
    "write_broker_config",
]

VIEWER = "viewer"
CERTIFICATE_DAYS = 365
"""Validity of generated certificates (CA, server, clients), days from generation."""
DEFAULT_QUEUE_BYTES = 64 * 1024 * 1024
DEFAULT_AUTOSAVE_S = 1
MAX_PACKET_BYTES = 1024 * 1024
SERVICE_USER = "mosquitto"
PBKDF2_ITERATIONS = 101
"""Mosquitto's own default for ``$7$`` hashes; the generated passwords are random 144-bit
tokens, so the iteration count is not what protects them."""


@dataclass(frozen=True)
class BrokerFiles:
    """Where :func:`write_broker_config` put things.

    Attributes:
        directory: the output folder.
        config: ``mosquitto.conf``.
        port: the listener port.
        bind: the listener address.
        tls: whether the listener speaks TLS.
        password_file: hashed passwords (None for an anonymous broker).
        acl_file: access control list (None for an anonymous broker).
        credentials_file: ``credentials.json`` with the clear-text passwords, mode 0600.
        persistence_directory: where mosquitto stores its database.
        ca_file: CA certificate clients use to verify the broker (TLS only).
        client_certificates: user -> (certificate, key) paths (TLS only).
        roles: user -> "camera" | "matcher" | "viewer".
        password_files: user -> a 0600 file holding only that user's password (for
            ``cblrs camera/matcher --password-file``; copy it to that client's machine).
        ca_key_file: the CA's private key (TLS only), outside the broker's folder.
        run_as: the user Mosquitto runs as when started as root.
    """

    directory: Path
    config: Path
    port: int
    bind: str
    tls: bool
    password_file: Path | None
    acl_file: Path | None
    credentials_file: Path | None
    persistence_directory: Path | None
    ca_file: Path | None = None
    client_certificates: dict[str, tuple[Path, Path]] = field(default_factory=dict)
    roles: dict[str, str] = field(default_factory=dict)
    password_files: dict[str, Path] = field(default_factory=dict)
    ca_key_file: Path | None = None
    run_as: str | None = None

    def credentials(self) -> dict[str, str]:
        """user -> password, read from the 0600 credentials file."""
        if self.credentials_file is None:
            return {}
        return json.loads(self.credentials_file.read_text())["passwords"]

    def settings(self, user: str | None = None, host: str | None = None, **options) -> MqttSettings:
        """Connection settings for ``user`` (None: anonymous), with its certificate under TLS.

        Extra keyword arguments go to :class:`MqttSettings` (timeouts, inflight window).
        """
        host = host or ("127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind)
        password = None
        if user is not None:
            credentials = self.credentials()
            if user not in credentials:
                raise BrokerError(f"no user {user!r} in {self.credentials_file}.")
            password = credentials[user]
        cert_file = key_file = None
        if self.tls and user in self.client_certificates:
            cert_file, key_file = self.client_certificates[user]
        return MqttSettings(
            host=host,
            port=self.port,
            username=user,
            password=password,
            ca_file=self.ca_file if self.tls else None,
            cert_file=cert_file,
            key_file=key_file,
            **options,
        )

    def to_dict(self) -> dict:
        return {
            "directory": str(self.directory),
            "config": str(self.config),
            "port": self.port,
            "bind": self.bind,
            "tls": self.tls,
            "password_file": _optional(self.password_file),
            "acl_file": _optional(self.acl_file),
            "credentials_file": _optional(self.credentials_file),
            "persistence_directory": _optional(self.persistence_directory),
            "ca_file": _optional(self.ca_file),
            "client_certificates": {
                user: {"certificate": str(cert), "key": str(key)}
                for user, (cert, key) in self.client_certificates.items()
            },
            "roles": dict(self.roles),
            "password_files": {user: str(path) for user, path in self.password_files.items()},
            "ca_key_file": _optional(self.ca_key_file),
            "run_as": self.run_as,
        }


def _optional(path: Path | None) -> str | None:
    return None if path is None else str(path)


def write_broker_config(
    directory: str | os.PathLike,
    cameras: Sequence[str],
    matchers: Sequence[str],
    *,
    port: int,
    plane_ids: Sequence[int] = (1,),
    tls: bool = False,
    persistence: bool = True,
    bind: str = "127.0.0.1",
    viewer: bool = True,
    allow_anonymous: bool = False,
    passwords: dict[str, str] | None = None,
    queue_bytes: int = DEFAULT_QUEUE_BYTES,
    autosave_s: int = DEFAULT_AUTOSAVE_S,
    run_as: str | None = None,
    ca_directory: str | os.PathLike | None = None,
) -> BrokerFiles:
    """Write a Mosquitto configuration for a set of cameras and matchers.

    Args:
        directory: output folder (created; existing files of the same names are replaced).
        cameras: camera ids; each becomes a user that may publish only
            ``cblrs/+/<camera>/detections`` and ``cblrs/+/<camera>/status``.
        matchers: matcher ids; each may read detections and status of the planes
            ``plane_ids`` and publish their tracks and its own matcher status.
        port: listener port.
        plane_ids: planes the matchers serve.
        tls: make the listener TLS-only with generated certificates; clients must present a
            certificate signed by the generated CA as well as their password.
        persistence: keep queued QoS 1 messages and sessions across broker restarts.
        bind: listener address (use ``0.0.0.0`` to accept other machines).
        viewer: add a read-only ``viewer`` user for tracks and status.
        allow_anonymous: no users, no ACL (local experiments and benchmarks only).
        passwords: fixed passwords for some users (default: random, from ``secrets``).
        queue_bytes: bytes of queued messages held per client (see the module docstring).
        autosave_s: seconds between two saves of the broker's database.
        run_as: the user Mosquitto switches to when started as root (default: the
            ``mosquitto`` user when generated as root; the files it reads are handed to it).
        ca_directory: where the CA's private key goes with ``tls`` (default ``<out>-ca``).

    Returns:
        The paths written.

    Raises:
        BrokerError: invalid names or limits, or an unknown ``run_as`` user.
    """
    directory = Path(directory).resolve()
    for name in cameras:
        validate_client_id(name, "camera id")
    for name in matchers:
        validate_client_id(name, "matcher id")
    users = list(cameras) + list(matchers) + ([VIEWER] if viewer else [])
    if len(set(users)) != len(users):
        raise BrokerError(f"camera, matcher and viewer names must be distinct, got {users}.")
    if not allow_anonymous and not (cameras or matchers):
        raise BrokerError("give at least one camera or matcher (or allow anonymous access).")
    planes = [int(plane) for plane in plane_ids]
    if not planes or any(not 1 <= plane <= 65535 for plane in planes):
        raise BrokerError(f"plane ids must be 1..65535, got {list(plane_ids)}.")
    if not 0 < port < 65536:
        raise BrokerError(f"port must be 1..65535, got {port}.")
    if queue_bytes <= 0:
        raise BrokerError(f"the queue limit must be positive, got {queue_bytes} bytes.")
    if autosave_s < 1:
        raise BrokerError(f"autosave interval must be at least 1 s, got {autosave_s}.")
    if run_as is None and os.geteuid() == 0:
        run_as = SERVICE_USER
    if run_as is not None and run_as != "root" and os.geteuid() == 0:
        _check_reachable(run_as, directory)
    directory.mkdir(parents=True, exist_ok=True)
    owner = None
    if run_as is not None:
        try:
            owner = pwd.getpwnam(run_as)
        except KeyError:
            raise BrokerError(
                f"there is no user {run_as!r} for Mosquitto to run as; create it (the Debian "
                "package does: apt install mosquitto) or choose another."
            ) from None
    roles = {name: "camera" for name in cameras}
    roles.update({name: "matcher" for name in matchers})
    if viewer:
        roles[VIEWER] = "viewer"

    lines = [
        "# Written by cblrs broker-config. Start with:",
        f"#   mosquitto -c {directory / 'mosquitto.conf'}",
        "per_listener_settings false",
        f"allow_anonymous {'true' if allow_anonymous else 'false'}",
        "log_dest stderr",
        "log_type error",
        "log_type warning",
        "log_type notice",
        "log_type information",
        "connection_messages true",
        "# Queue per client: bounded in bytes, not in count; a full queue drops messages after",
        "# acknowledging them, so the cameras keep theirs until the matcher confirms them.",
        "max_queued_messages 0",
        f"max_queued_bytes {int(queue_bytes)}",
        "max_inflight_messages 100",
        f"max_packet_size {MAX_PACKET_BYTES}",
        "set_tcp_nodelay true",
    ]
    if run_as is not None:
        lines.append(f"user {run_as}")
    password_file = acl_file = credentials_file = None
    password_files: dict[str, Path] = {}
    if not allow_anonymous:
        password_file = directory / "passwords"
        acl_file = directory / "acl"
        credentials_file = directory / "credentials.json"
        chosen = dict(passwords or {})
        credentials = {user: chosen.get(user) or secrets.token_urlsafe(18) for user in users}
        _write_passwords(password_file, credentials)
        _write_private(
            credentials_file,
            json.dumps({"passwords": credentials, "roles": roles}, indent=2) + "\n",
        )
        secrets_directory = directory / "secrets"
        secrets_directory.mkdir(exist_ok=True)
        os.chmod(secrets_directory, 0o700)
        for user, password in credentials.items():
            password_files[user] = secrets_directory / f"{user}.password"
            _write_private(password_files[user], password + "\n")
        acl_file.write_text(_acl(cameras, matchers, planes, viewer))
        lines += [
            f"password_file {password_file}",
            f"acl_file {acl_file}",
        ]
    persistence_directory = None
    if persistence:
        persistence_directory = directory / "data"
        persistence_directory.mkdir(exist_ok=True)
        lines += [
            "persistence true",
            f"persistence_location {persistence_directory}/",
            "# Saved once more than autosave_interval whole seconds have passed, and on a clean",
            "# stop (SIGTERM); a kill -9 loses what came since the last completed save began",
            "# (2-4 s), which the cameras' spools still hold until the matcher confirms it.",
            f"autosave_interval {int(autosave_s)}",
        ]
    else:
        lines.append("persistence false")
    lines.append("")
    lines.append(f"listener {port} {bind}")
    lines.append("protocol mqtt")
    if not allow_anonymous:
        # A listener option (outside a listener block it would open a default one on 1883):
        # the session is the user's, so nobody takes over a matcher's queue with its client id.
        lines.append("use_username_as_clientid true")
    ca_file = None
    client_certificates: dict[str, tuple[Path, Path]] = {}
    ca_key_file = None
    if tls:
        tls_directory = directory / "tls"
        ca_keys = Path(ca_directory) if ca_directory is not None else directory.with_name(
            directory.name + "-ca")
        ca_keys = ca_keys.resolve()
        if ca_keys == directory or directory in ca_keys.parents:
            raise BrokerError(f"the CA's key folder {ca_keys} must lie outside {directory}.")
        ca_file, server_cert, server_key, client_certificates, ca_key_file = _write_certificates(
            tls_directory, users, bind, ca_keys
        )
        lines += [
            f"cafile {ca_file}",
            f"certfile {server_cert}",
            f"keyfile {server_key}",
            "require_certificate true",
            "# The certificate's common name is the user: it cannot be paired with another's",
            "# login (the password file is not used on this listener).",
            "use_identity_as_username true",
            "tls_version tlsv1.2",
        ]
    config = directory / "mosquitto.conf"
    config.write_text("\n".join(lines) + "\n")
    if owner is not None and os.geteuid() == 0:
        _hand_over(owner, directory, [config, password_file, acl_file, persistence_directory]
                   + ([directory / "tls", directory / "tls" / "server.key"] if tls else []))
    return BrokerFiles(
        directory=directory,
        config=config,
        port=port,
        bind=bind,
        tls=tls,
        password_file=password_file,
        acl_file=acl_file,
        credentials_file=credentials_file,
        persistence_directory=persistence_directory,
        ca_file=ca_file,
        client_certificates=client_certificates,
        roles=roles,
        password_files=password_files,
        ca_key_file=ca_key_file,
        run_as=run_as,
    )


def _hand_over(owner: pwd.struct_passwd, directory: Path, paths: list[Path | None]) -> None:
    """Give the broker's user the folder and the files it must read (or write: data/)."""
    for path in [directory, *paths]:
        if path is not None and path.exists():
            os.chown(path, owner.pw_uid, owner.pw_gid)


def _check_reachable(user: str, directory: Path) -> None:
    """Raise unless ``user`` may pass through every existing folder above ``directory``."""
    try:
        owner = pwd.getpwnam(user)
    except KeyError:
        raise BrokerError(
            f"there is no user {user!r} for Mosquitto to run as; create it (the Debian "
            "package does: apt install mosquitto) or choose another."
        ) from None
    for parent in reversed(directory.parents):
        try:
            info = parent.stat()
        except OSError:
            return  # not created yet: mkdir makes it 0755
        if info.st_uid == owner.pw_uid:
            allowed = bool(info.st_mode & stat.S_IXUSR)
        elif info.st_gid == owner.pw_gid:
            allowed = bool(info.st_mode & stat.S_IXGRP)
        else:
            allowed = bool(info.st_mode & stat.S_IXOTH)
        if not allowed:
            raise BrokerError(
                f"Mosquitto runs as user {user}, which cannot enter {parent} (mode "
                f"{stat.S_IMODE(info.st_mode):o}) to read {directory}: write the configuration "
                "where it can (e.g. under /etc/cblrs), or choose the user with --run-as."
            )


def _acl(cameras: Sequence[str], matchers: Sequence[str], planes: list[int], viewer: bool) -> str:
    """Mosquitto ACL: default deny; each user gets only the topics of its role."""
    lines = ["# Written by cblrs broker-config; anything not granted here is denied.", ""]
    for camera in cameras:
        lines += [
            f"user {camera}",
            f"topic write {ROOT}/+/{camera}/detections",
            f"topic write {ROOT}/+/{camera}/status",
            f"topic read {ROOT}/+/{camera}/stored",
            f"topic read {ROOT}/+/matchers/+/status",
            "",
        ]
    for matcher in matchers:
        lines.append(f"user {matcher}")
        for plane in planes:
            lines += [
                f"topic read {ROOT}/{plane}/+/detections",
                f"topic read {ROOT}/{plane}/+/status",
                f"topic write {ROOT}/{plane}/tracks",
                f"topic write {ROOT}/{plane}/events",
                f"topic write {ROOT}/{plane}/live",
                f"topic write {ROOT}/{plane}/+/stored",
                f"topic write {ROOT}/{plane}/matchers/{matcher}/status",
                f"topic readwrite {ROOT}/{plane}/lease",
            ]
        lines.append("")
    if viewer:
        lines += [
            f"user {VIEWER}",
            f"topic read {ROOT}/+/tracks",
            f"topic read {ROOT}/+/events",
            f"topic read {ROOT}/+/live",
            f"topic read {ROOT}/+/+/status",
            f"topic read {ROOT}/+/matchers/+/status",
            f"topic read {ROOT}/+/lease",
            "",
        ]
    return "\n".join(lines)


def _write_private(path: Path, text: str) -> None:
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w") as handle:
        handle.write(text)
    os.chmod(path, 0o600)


def _write_passwords(path: Path, credentials: dict[str, str]) -> None:
    """Mosquitto's password file, hashed here (``$7$``: PBKDF2-SHA512, 12-byte salt): no
    clear password ever appears on a command line (``mosquitto_passwd -b`` shows it in
    ``ps``)."""
    lines = [f"{user}:{hash_password(password)}" for user, password in credentials.items()]
    _write_private(path, "\n".join(lines) + "\n")


def hash_password(password: str, salt: bytes | None = None) -> str:
    """A Mosquitto ``$7$`` password hash (what ``mosquitto_passwd`` writes)."""
    salt = secrets.token_bytes(12) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, PBKDF2_ITERATIONS)
    return (f"$7${PBKDF2_ITERATIONS}${base64.b64encode(salt).decode()}$"
            f"{base64.b64encode(digest).decode()}")


def _write_certificates(
    directory: Path, users: Sequence[str], bind: str, ca_directory: Path
) -> tuple[Path, Path, Path, dict[str, tuple[Path, Path]], Path]:
    """A CA, a server certificate (SAN localhost, 127.0.0.1, the bind address) and one client
    certificate per user (CN = user), ECDSA P-256, valid :data:`CERTIFICATE_DAYS` days; the
    CA's key goes to ``ca_directory`` (mode 0700), not beside the broker's files."""
    try:
        # optional extra: pip install cblrs[tls]
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError as error:
        raise BrokerError(
            "TLS certificates need the cryptography package: pip install cryptography."
        ) from error
    directory.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    until = now + datetime.timedelta(days=CERTIFICATE_DAYS)

    def name(common_name: str) -> x509.Name:
        return x509.Name(
            [
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cblrs"),
                x509.NameAttribute(NameOID.COMMON_NAME, common_name),
            ]
        )

    def save(stem: str, certificate, key) -> tuple[Path, Path]:
        cert_path = directory / f"{stem}.crt"
        key_path = directory / f"{stem}.key"
        cert_path.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
        _write_private(
            key_path,
            key.private_bytes(
                serialization.Encoding.PEM,
                serialization.PrivateFormat.PKCS8,
                serialization.NoEncryption(),
            ).decode(),
        )
        return cert_path, key_path

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name("cblrs broker CA")
    ca_certificate = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    ca_file = directory / "ca.crt"
    ca_file.write_bytes(ca_certificate.public_bytes(serialization.Encoding.PEM))
    ca_directory.mkdir(parents=True, exist_ok=True)
    os.chmod(ca_directory, 0o700)
    ca_key_file = ca_directory / "ca.key"
    _write_private(
        ca_key_file,
        ca_key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        ).decode(),
    )
    stale = directory / "ca.key"
    if stale.exists():  # from a configuration written before the key moved out
        stale.unlink()

    def issue(common_name: str, server: bool):
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (
            x509.CertificateBuilder()
            .subject_name(name(common_name))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(until)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
        )
        if server:
            alternative: list[x509.GeneralName] = [
                x509.DNSName("localhost"),
                x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
            ]
            try:
                address = ipaddress.ip_address(bind)
                if str(address) not in ("127.0.0.1", "0.0.0.0", "::"):
                    alternative.append(x509.IPAddress(address))
            except ValueError:
                alternative.append(x509.DNSName(bind))
            builder = builder.add_extension(
                x509.SubjectAlternativeName(alternative), critical=False
            )
        return builder.sign(ca_key, hashes.SHA256()), key

    server_cert, server_key = save("server", *issue("localhost", server=True))
    clients = {user: save(f"client-{user}", *issue(user, server=False)) for user in users}
    return ca_file, server_cert, server_key, clients, ca_key_file
