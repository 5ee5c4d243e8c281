"""Mosquitto configuration for the runtime: users, ACL, TLS, persistence; and a process wrapper.

:func:`write_broker_config` writes what a broker needs into one directory, and what each
client needs into a folder of its own (see :mod:`cblrs.runtime.broker.credentials`)::

    <out>/mosquitto.conf  listener, allow_anonymous false, password_file, acl_file,
                          persistence, queue and message limits
    <out>/passwords       PBKDF2-SHA512 hashes in Mosquitto's ``$7$`` format, computed here
                          (no clear password on any command line, none stored here)
    <out>/acl             a camera publishes only its own detections and status and reads
                          only its confirmations and the matchers' status; a matcher reads
                          the detections of its planes, publishes their tracks, analytics
                          events, live summaries, alerts and confirmations and holds their
                          lease; a viewer (a dashboard) reads every plane's tracks,
                          events, live summaries, alerts and camera and matcher status,
                          the linker's (plane 0: global tracks, site counts, its
                          status), and writes nothing; a linker reads every plane's
                          tracks and publishes the site's (plane 0)
    <out>/data/           persistence (queued QoS 1 messages survive a broker restart)
    <out>/tls/            the CA certificate, the server's certificate and key (``tls=True``)
    <out>-clients/<user>/ one client's password, and with TLS its certificate, key and the CA
                          certificate (0700/0600): copy that folder to that client only
    <out>-ca/             the CA's private key (TLS), never in the broker's folder

**One login, one client.** The listener uses the login as the MQTT client id
(``use_username_as_clientid``): nobody takes over another user's session with its client id.
The flip side is that two clients with one login share one session and take it from each
other, so no login may be shared: every dashboard gets its own viewer login (``viewers``);
a transport that loses its session to another client says so loudly and counts it
(:attr:`~cblrs.runtime.transport.mqtt_transport.MqttTransport.takeovers`).

Policies (the broker is a short buffer; each camera's disk spool is the long one, see
:mod:`cblrs.runtime.camera.spool`):

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

:class:`~cblrs.runtime.broker.mosquitto.MosquittoProcess` (in :mod:`cblrs.runtime.broker.mosquitto`,
and importable from here) runs ``mosquitto -c mosquitto.conf`` as a child process.

It stays one module because the configuration, the ACL, the password file and the certificates
are one generated folder whose files name each other; running Mosquitto is in
:mod:`cblrs.runtime.broker.mosquitto`.
"""

from __future__ import annotations

import logging
import os
import pwd
import stat
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cblrs.runtime.addresses import is_loopback_host
from cblrs.runtime.broker.credentials import (
    ClientFiles,
    CredentialsError,
    check_outside,
    default_side_folder,
    mosquitto_hash,
    new_authority,
    new_password,
    write_client_folder,
    write_private,
)
from cblrs.runtime.broker.credentials import issue_certificate as _issue
from cblrs.runtime.broker.mosquitto import BrokerError, MosquittoProcess, find_mosquitto, free_port
from cblrs.runtime.transport.mqtt_transport import MqttSettings
from cblrs.runtime.transport.topics import ROOT, validate_client_id

logger = logging.getLogger(__name__)

__all__ = [
    "BrokerError",
    "BrokerFiles",
    "MosquittoProcess",
    "find_mosquitto",
    "free_port",
    "hash_password",
    "matcher_planes",
    "write_broker_config",
]

VIEWER = "viewer"
DEFAULT_QUEUE_BYTES = 64 * 1024 * 1024
DEFAULT_AUTOSAVE_S = 1
MAX_PACKET_BYTES = 1024 * 1024
SERVICE_USER = "mosquitto"
hash_password = mosquitto_hash
"""A Mosquitto ``$7$`` password hash (:func:`cblrs.runtime.broker.credentials.mosquitto_hash`)."""


@dataclass(frozen=True)
class BrokerFiles:
    """Where :func:`write_broker_config` put things.

    Attributes:
        directory: the broker's folder (nothing secret but its own key and the hashes).
        config: ``mosquitto.conf``.
        port: the listener port.
        bind: the listener address.
        tls: whether the listener speaks TLS.
        password_file: hashed passwords (None for an anonymous broker).
        acl_file: access control list (None for an anonymous broker).
        persistence_directory: where mosquitto stores its database.
        ca_file: CA certificate that signed the broker's (TLS only).
        roles: user -> "camera" | "matcher" | "viewer".
        clients: user -> its folder of secrets (see :class:`ClientFiles`): copy each to that
            client only.
        clients_directory: the folder holding every client's folder (outside ``directory``).
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
    persistence_directory: Path | None
    ca_file: Path | None = None
    roles: dict[str, str] = field(default_factory=dict)
    clients: dict[str, ClientFiles] = field(default_factory=dict)
    clients_directory: Path | None = None
    ca_key_file: Path | None = None
    run_as: str | None = None

    @property
    def password_files(self) -> dict[str, Path]:
        """user -> the 0600 file holding only that user's password (in its client folder)."""
        return {user: files.password_file for user, files in self.clients.items()
                if files.password_file is not None}

    @property
    def client_certificates(self) -> dict[str, tuple[Path, Path]]:
        """user -> (certificate, key) paths in its client folder (TLS only)."""
        return {user: (files.cert_file, files.key_file) for user, files in self.clients.items()
                if files.cert_file is not None and files.key_file is not None}

    def credentials(self) -> dict[str, str]:
        """user -> password, read from the clients' folders (while they are still here)."""
        return {user: password for user, files in self.clients.items()
                if (password := files.password()) is not None}

    def settings(self, user: str | None = None, host: str | None = None, **options) -> MqttSettings:
        """Connection settings for ``user`` (None: anonymous), with its certificate under TLS.

        Extra keyword arguments go to :class:`MqttSettings` (timeouts, inflight window).
        """
        host = host or ("127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind)
        password = cert_file = key_file = None
        if user is not None:
            if user not in self.clients:
                raise BrokerError(f"no user {user!r} in {self.clients_directory}.")
            client = self.clients[user]
            password = client.password()
            cert_file, key_file = client.cert_file, client.key_file
        return MqttSettings(
            host=host,
            port=self.port,
            username=user,
            password=password,
            ca_file=self.ca_file if self.tls else None,
            cert_file=cert_file if self.tls else None,
            key_file=key_file if self.tls else None,
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
            "persistence_directory": _optional(self.persistence_directory),
            "ca_file": _optional(self.ca_file),
            "roles": dict(self.roles),
            "clients": {user: files.to_dict() for user, files in self.clients.items()},
            "clients_directory": _optional(self.clients_directory),
            "ca_key_file": _optional(self.ca_key_file),
            "run_as": self.run_as,
        }


def _optional(path: Path | None) -> str | None:
    return None if path is None else str(path)


def matcher_planes(
    matchers: Sequence[str] | Mapping[str, Sequence[int]], plane_ids: Sequence[int]
) -> dict[str, list[int]]:
    """matcher -> the planes it may serve: ``matchers`` as given when a mapping, else every
    matcher serves every plane of ``plane_ids``.

    Raises:
        BrokerError: a plane id outside 1..65535, or a matcher without planes.
    """
    if isinstance(matchers, Mapping):
        planes = {name: [int(plane) for plane in served] for name, served in matchers.items()}
    else:
        planes = {name: [int(plane) for plane in plane_ids] for name in matchers}
    for name, served in planes.items():
        if not served:
            raise BrokerError(f"matcher {name} serves no plane; give it at least one.")
        if any(not 1 <= plane <= 65535 for plane in served):
            raise BrokerError(f"plane ids must be 1..65535, got {served}.")
    return planes


def write_broker_config(
    directory: str | os.PathLike,
    cameras: Sequence[str],
    matchers: Sequence[str] | Mapping[str, Sequence[int]],
    *,
    port: int,
    plane_ids: Sequence[int] = (1,),
    tls: bool = False,
    persistence: bool = True,
    bind: str = "127.0.0.1",
    viewer: bool = True,
    viewers: Sequence[str] | None = None,
    linkers: Sequence[str] = (),
    allow_anonymous: bool = False,
    passwords: dict[str, str] | None = None,
    queue_bytes: int = DEFAULT_QUEUE_BYTES,
    autosave_s: int = DEFAULT_AUTOSAVE_S,
    run_as: str | None = None,
    ca_directory: str | os.PathLike | None = None,
    clients_directory: str | os.PathLike | None = None,
    allow_plaintext: bool = False,
) -> BrokerFiles:
    """Write a Mosquitto configuration for a set of cameras, matchers and viewers.

    Args:
        directory: the broker's folder (created; files of the same names are replaced).
        cameras: camera ids; each becomes a user that may publish only
            ``cblrs/+/<camera>/detections`` and ``cblrs/+/<camera>/status``.
        matchers: matcher ids (each serving every plane of ``plane_ids``), or matcher id ->
            the planes it serves; a matcher may read the detections and status of its
            planes and publish their tracks, events, live summaries, alerts and confirmations.
        port: listener port.
        plane_ids: planes the matchers serve (when ``matchers`` is not a mapping).
        tls: make the listener TLS-only with generated certificates; clients must present a
            certificate signed by the generated CA as well as their password.
        persistence: keep queued QoS 1 messages and sessions across broker restarts.
        bind: listener address (use ``0.0.0.0`` to accept other machines).
        viewer: add a read-only ``viewer`` user for tracks and status.
        viewers: read-only logins, one per dashboard (default ``["viewer"]`` when
            ``viewer``); a login is one client at a time (see the module docstring).
        linkers: logins of ``cblrs linker`` (one per site): each reads every plane's track
            updates and publishes the site's global tracks, events, live summary and its
            own status (plane 0).
        allow_anonymous: no users, no ACL (local experiments and benchmarks only).
        passwords: fixed passwords for some users (default: random, from ``secrets``).
        queue_bytes: bytes of queued messages held per client (see the module docstring).
        autosave_s: seconds between two saves of the broker's database.
        run_as: the user Mosquitto switches to when started as root (default: the
            ``mosquitto`` user when generated as root; the files it reads are handed to it).
        ca_directory: where the CA's private key goes with ``tls`` (default ``<out>-ca``).
        clients_directory: where each client's folder goes (default ``<out>-clients``).
        allow_plaintext: accept a listener beyond loopback without TLS (the passwords and
            every message then cross the network in clear: for a network already encrypted
            and trusted, e.g. a VPN).

    Returns:
        The paths written.

    Raises:
        BrokerError: invalid names or limits, an unknown ``run_as`` user, or a listener
            beyond loopback without TLS (unless ``allow_plaintext``).
    """
    directory = Path(directory).resolve()
    for name in cameras:
        validate_client_id(name, "camera id")
    if not plane_ids or any(not 1 <= int(plane) <= 65535 for plane in plane_ids):
        raise BrokerError(f"plane ids must be 1..65535, got {list(plane_ids)}.")
    planes_of = matcher_planes(matchers, plane_ids)
    for name in planes_of:
        validate_client_id(name, "matcher id")
    viewer_names = list(viewers) if viewers is not None else ([VIEWER] if viewer else [])
    for name in viewer_names:
        validate_client_id(name, "viewer id")
    for name in linkers:
        validate_client_id(name, "linker id")
    users = list(cameras) + list(planes_of) + viewer_names + list(linkers)
    if len(set(users)) != len(users):
        raise BrokerError(f"camera, matcher, viewer and linker names must be distinct, got "
                          f"{users}.")
    if not allow_anonymous and not (cameras or planes_of):
        raise BrokerError("give at least one camera or matcher (or allow anonymous access).")
    if not 0 < port < 65536:
        raise BrokerError(f"port must be 1..65535, got {port}.")
    if not tls and not allow_plaintext and not is_loopback_host(bind):
        raise BrokerError(
            f"a listener on {bind} without TLS would take passwords and detections across "
            "the network in clear: add TLS (--tls), or --allow-plaintext for a network that "
            "is already encrypted and trusted.")
    if queue_bytes <= 0:
        raise BrokerError(f"the queue limit must be positive, got {queue_bytes} bytes.")
    if autosave_s < 1:
        raise BrokerError(f"autosave interval must be at least 1 s, got {autosave_s}.")
    try:
        clients_folder = check_outside(
            Path(clients_directory) if clients_directory is not None
            else default_side_folder(directory, "clients"), directory, "clients'")
        ca_keys = check_outside(
            Path(ca_directory) if ca_directory is not None
            else default_side_folder(directory, "ca"), directory, "CA's key")
    except CredentialsError as error:
        raise BrokerError(str(error)) from None
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
    roles.update({name: "matcher" for name in planes_of})
    roles.update({name: "viewer" for name in viewer_names})
    roles.update({name: "linker" for name in linkers})

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
    password_file = acl_file = None
    chosen_passwords: dict[str, str | None] = {}
    if not allow_anonymous:
        password_file = directory / "passwords"
        acl_file = directory / "acl"
        chosen = dict(passwords or {})
        credentials = {user: chosen.get(user) or new_password() for user in users}
        _write_passwords(password_file, credentials)
        chosen_passwords = dict(credentials)
        stale = [directory / "credentials.json", directory / "secrets"]
        _remove_stale(stale)  # clear passwords left by an older cblrs
        write_private(acl_file, _acl(cameras, planes_of, viewer_names, linkers))
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
        # the session is the user's, so nobody takes over a matcher's queue with its client
        # id; and so each login is one client (a dashboard gets a viewer login of its own).
        lines.append("use_username_as_clientid true")
    ca_file = ca_key_file = None
    authority = None
    if tls:
        tls_directory = directory / "tls"
        authority = new_authority("cblrs broker CA", tls_directory / "ca.crt", ca_keys)
        ca_file, ca_key_file = authority.certificate_file, authority.key_file
        stale_key = tls_directory / "ca.key"
        if stale_key.exists():  # from a configuration written before the key moved out
            stale_key.unlink()
        _remove_stale(list(tls_directory.glob("client-*")))  # keys of an older cblrs
        certificate, key = _issue(authority, "localhost", server=True, client=False,
                                  hosts=[bind])
        server_cert = tls_directory / "server.crt"
        server_cert.write_bytes(certificate)
        server_key = write_private(tls_directory / "server.key", key)
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
    clients: dict[str, ClientFiles] = {}
    if not allow_anonymous:
        for user in users:
            clients[user] = write_client_folder(
                clients_folder, user, chosen_passwords.get(user), authority)
    config = write_private(directory / "mosquitto.conf", "\n".join(lines) + "\n")
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
        persistence_directory=persistence_directory,
        ca_file=ca_file,
        roles=roles,
        clients=clients,
        clients_directory=clients_folder if clients else None,
        ca_key_file=ca_key_file,
        run_as=run_as,
    )


def _remove_stale(paths: list[Path]) -> None:
    import shutil

    for path in paths:
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


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


def _acl(cameras: Sequence[str], planes_of: Mapping[str, Sequence[int]],
         viewers: Sequence[str], linkers: Sequence[str] = ()) -> str:
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
    for matcher, planes in planes_of.items():
        lines.append(f"user {matcher}")
        for plane in planes:
            lines += [
                f"topic read {ROOT}/{plane}/+/detections",
                f"topic read {ROOT}/{plane}/+/status",
                f"topic write {ROOT}/{plane}/tracks",
                f"topic write {ROOT}/{plane}/events",
                f"topic write {ROOT}/{plane}/live",
                f"topic write {ROOT}/{plane}/alerts",
                f"topic write {ROOT}/{plane}/+/stored",
                f"topic write {ROOT}/{plane}/matchers/{matcher}/status",
                f"topic readwrite {ROOT}/{plane}/lease",
            ]
        lines.append("")
    for viewer in viewers:
        lines += [
            f"user {viewer}",
            f"topic read {ROOT}/+/tracks",
            f"topic read {ROOT}/+/events",
            f"topic read {ROOT}/+/live",
            f"topic read {ROOT}/+/alerts",
            f"topic read {ROOT}/+/+/status",
            f"topic read {ROOT}/+/matchers/+/status",
            f"topic read {ROOT}/0/linkers/+/status",
            f"topic read {ROOT}/+/lease",
            "",
        ]
    for linker in linkers:
        lines += [
            f"user {linker}",
            f"topic read {ROOT}/+/tracks",
            f"topic write {ROOT}/0/tracks",
            f"topic write {ROOT}/0/events",
            f"topic write {ROOT}/0/live",
            f"topic write {ROOT}/0/linkers/{linker}/status",
            "",
        ]
    return "\n".join(lines)


def _write_passwords(path: Path, credentials: dict[str, str]) -> None:
    """Mosquitto's password file, hashed here (``$7$``: PBKDF2-SHA512, 12-byte salt): no
    clear password ever appears on a command line (``mosquitto_passwd -b`` shows it in
    ``ps``)."""
    lines = [f"{user}:{mosquitto_hash(password)}" for user, password in credentials.items()]
    write_private(path, "\n".join(lines) + "\n")
