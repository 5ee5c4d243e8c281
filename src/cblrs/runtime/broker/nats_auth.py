"""NATS users, permissions and TLS for the backbone: the NATS side of ``cblrs broker-config``.

:func:`write_nats_security` generates, for a set of cameras, matchers and viewers (and one
administrator), what a NATS server or cluster needs to refuse everyone else, mirroring the
Mosquitto ACL of :mod:`cblrs.runtime.broker.mosquitto_config`:

* **users** with bcrypt-hashed passwords (the server's folder holds no clear password), no
  anonymous access (no ``no_auth_user``), and the same users on the server's MQTT listener;
* **permissions** per role (:func:`role_permissions`; ``R`` is ``cblrs`` or
  ``cblrs.<site>``, ``DS`` the plane's detections stream, ``D`` its consumer)::

      camera C   publish  R.*.C.detections, R.*.C.status
                 read     R.*.C.stored, R.*.matchers.*.status, its own inbox
      matcher M  publish  R.P.tracks|events|live|alerts, R.P.*.stored, R.P.matchers.M.status
                 (for each plane P it serves); its consumer only:
                 $JS.API.CONSUMER.INFO|RESET|MSG.NEXT.DS.D, $JS.ACK.DS.D.>; its lease
                 key only: $KV.cblrs_leases.KEY, $JS.API.DIRECT.GET.KV_cblrs_leases.
                 $KV.cblrs_leases.KEY, $JS.API.STREAM.INFO.KV_cblrs_leases
                 read     its own inbox
      viewer V   read     R.*.tracks|events|live|alerts, R.*.*.status, R.*.matchers.*.status,
                 R.0.linkers.*.status (every plane's, and the linker's: plane 0)
                 publish  nothing
      linker L   publish  R.0.tracks|events|live, R.0.linkers.L.status; its consumers only
                 (``LC`` = ``cblrs-linker-L``, on each plane P's tracks stream ``TS``):
                 $JS.API.CONSUMER.INFO|RESET|MSG.NEXT.TS.LC, $JS.ACK.TS.LC.>
                 read     R.*.tracks, its own inbox
      admin      everything (streams, consumers, buckets: ``cblrs matcher --prepare``)

  Answers (JetStream acknowledgements, pulled messages) reach a client on its own inbox
  prefix ``_INBOX.<user>`` (:attr:`NatsSettings.inbox_prefix`), so nobody reads another's.
  Nobody but the admin may create, change or delete a stream, a consumer or a bucket: a
  matcher (a linker) may only read its consumer (its consumers), pull from it, acknowledge
  and reset it to replay the stream (a reset cannot point the consumer elsewhere; creating
  one could set a delivery subject that writes into another plane: a linker allowed to
  create its own consumer could have plane 1's track updates delivered into plane 2's
  tracks stream). The admin creates them: ``cblrs matcher --prepare``, ``cblrs linker
  --prepare``;
* **TLS** (``tls=True``): a CA signs the servers' certificate (SAN: the nodes' hosts) and one
  certificate per client (``verify``: a client without one is refused before it logs in);
  the routes between nodes use certificates of a *second* CA that only nodes hold, so a
  client's certificate cannot join the cluster as a route (which would bypass every
  permission).

Clients' secrets go to per-client folders (:mod:`cblrs.runtime.broker.credentials`), the CAs'
keys to a folder of their own; :func:`cblrs.runtime.broker.nats_server.write_nats_config` puts
the ``authorization`` block and the TLS blocks into each node's configuration.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError
from cblrs.runtime.broker.credentials import (
    Authority,
    ClientFiles,
    CredentialsError,
    bcrypt_hash,
    check_outside,
    default_side_folder,
    issue_certificate,
    new_authority,
    new_password,
    write_client_folder,
    write_private,
)
from cblrs.runtime.transport.mqtt_transport import MqttSettings
from cblrs.runtime.transport.nats_fanin import linker_consumer
from cblrs.runtime.transport.nats_settings import NatsSettings
from cblrs.runtime.transport.nats_subjects import (
    LEASE_BUCKET,
    detections_stream,
    lease_key,
    subject_root,
    tracks_stream,
    validate_site,
)
from cblrs.runtime.transport.protocol import TransportError
from cblrs.runtime.transport.topics import validate_client_id

ADMIN = "admin"
VIEWER = "viewer"


class NatsSecurityError(CblrsError):
    """The NATS users, permissions or certificates could not be generated."""


def _token(name: str) -> str:
    """A client id as one subject token (``.`` is ``//`` on the wire, as in topics)."""
    return name.replace(".", "//")


def consumer_name(plane_id: int) -> str:
    """The durable consumer of a plane's detections stream: ``cblrs-plane-<plane>``."""
    return f"cblrs-plane-{plane_id}"


def role_permissions(
    role: str, name: str, planes: Sequence[int] = (), site: str | None = None
) -> dict[str, dict[str, list[str]]] | None:
    """The NATS permissions of one user (None: the admin, who may do everything).

    Args:
        role: "camera", "matcher", "viewer", "linker" or "admin".
        name: the user (a camera's or matcher's id).
        planes: the planes a matcher serves, or whose tracks a linker reads.
        site: the site id of the subjects (None: ``cblrs.<plane>...``).
    """
    root = subject_root(site)
    own = _token(name)
    inbox = f"_INBOX.{own}.>"
    if role == "admin":
        return None
    if role == "camera":
        return {
            "publish": {"allow": [f"{root}.*.{own}.detections", f"{root}.*.{own}.status"]},
            "subscribe": {"allow": [f"{root}.*.{own}.stored", f"{root}.*.matchers.*.status",
                                    inbox]},
        }
    if role == "matcher":
        publish = [f"$JS.API.STREAM.INFO.KV_{LEASE_BUCKET}"]
        for plane in planes:
            stream, consumer = detections_stream(plane, site), consumer_name(plane)
            key = f"$KV.{LEASE_BUCKET}.{lease_key(plane, site)}"
            publish += [
                f"{root}.{plane}.tracks",
                f"{root}.{plane}.events",
                f"{root}.{plane}.live",
                f"{root}.{plane}.alerts",
                f"{root}.{plane}.*.stored",
                f"{root}.{plane}.matchers.{own}.status",
                f"$JS.API.CONSUMER.INFO.{stream}.{consumer}",
                f"$JS.API.CONSUMER.RESET.{stream}.{consumer}",
                f"$JS.API.CONSUMER.MSG.NEXT.{stream}.{consumer}",
                f"$JS.ACK.{stream}.{consumer}.>",
                key,
                f"$JS.API.DIRECT.GET.KV_{LEASE_BUCKET}.{key}",
            ]
        return {"publish": {"allow": publish}, "subscribe": {"allow": [inbox]}}
    if role == "viewer":
        return {
            "publish": {"deny": [">"]},
            "subscribe": {"allow": [f"{root}.*.tracks", f"{root}.*.events", f"{root}.*.live",
                                    f"{root}.*.alerts", f"{root}.*.*.status",
                                    f"{root}.*.matchers.*.status",
                                    f"{root}.0.linkers.*.status", inbox]},
        }
    if role == "linker":
        publish = [f"{root}.0.tracks", f"{root}.0.events", f"{root}.0.live",
                   f"{root}.0.linkers.{own}.status"]
        consumer = linker_consumer(name)
        for plane in planes:
            stream = tracks_stream(plane, site)
            publish += [
                f"$JS.API.CONSUMER.INFO.{stream}.{consumer}",
                f"$JS.API.CONSUMER.RESET.{stream}.{consumer}",
                f"$JS.API.CONSUMER.MSG.NEXT.{stream}.{consumer}",
                f"$JS.ACK.{stream}.{consumer}.>",
            ]
        return {"publish": {"allow": publish},
                "subscribe": {"allow": [f"{root}.*.tracks", inbox]}}
    raise ValueError(f"unknown role {role!r}")


@dataclass(frozen=True)
class NatsSecurity:
    """What :func:`write_nats_security` wrote.

    Attributes:
        directory: the servers' folder (hashes, the servers' certificates and keys).
        users: user -> (role, bcrypt hash, permissions or None for the admin).
        roles: user -> "camera" | "matcher" | "viewer" | "admin".
        clients: user -> its folder of secrets: copy each to that client only.
        clients_directory: the folder of the clients' folders (outside ``directory``).
        site: the site id of the subjects (None: no prefix).
        tls: whether clients and routes speak TLS.
        ca_file: the CA certificate clients verify the servers with (TLS).
        server_cert_file: the servers' certificate (TLS).
        server_key_file: its key (TLS, 0600).
        route_ca_file: the routes' CA certificate (TLS, a cluster's nodes only).
        route_cert_file: the nodes' route certificate (TLS).
        route_key_file: its key (TLS, 0600).
        ca_key_directory: where the CAs' keys went (TLS), outside ``directory``.
    """

    directory: Path
    users: dict[str, tuple[str, str, dict | None]]
    roles: dict[str, str]
    clients: dict[str, ClientFiles]
    clients_directory: Path
    site: str | None = None
    tls: bool = False
    ca_file: Path | None = None
    server_cert_file: Path | None = None
    server_key_file: Path | None = None
    route_ca_file: Path | None = None
    route_cert_file: Path | None = None
    route_key_file: Path | None = None
    ca_key_directory: Path | None = None
    hosts: tuple[str, ...] = field(default=("127.0.0.1",))

    def authorization_lines(self) -> list[str]:
        """The ``authorization { users = [...] }`` block of a node's configuration."""
        lines = ["authorization {", "  users = ["]
        for user, (_, hashed, permissions) in self.users.items():
            entry = f'    {{user: {_quote(user)}, password: {_quote(hashed)}'
            if permissions is not None:
                entry += f", permissions: {_conf(permissions)}"
            lines.append(entry + "}")
        lines += ["  ]", "}"]
        return lines

    def tls_lines(self, indent: str = "", route: bool = False) -> list[str]:
        """A ``tls { ... }`` block: the clients' (or, with ``route``, the routes')."""
        if not self.tls:
            return []
        cert, key, ca = ((self.route_cert_file, self.route_key_file, self.route_ca_file)
                         if route else (self.server_cert_file, self.server_key_file,
                                        self.ca_file))
        return [
            f"{indent}tls {{",
            f"{indent}  cert_file: {_quote(str(cert))}",
            f"{indent}  key_file: {_quote(str(key))}",
            f"{indent}  ca_file: {_quote(str(ca))}",
            f"{indent}  verify: true",
            f"{indent}  timeout: 5",
            f"{indent}}}",
        ]

    def credentials(self) -> dict[str, str]:
        """user -> password, from the clients' folders (while they are still here)."""
        return {user: password for user, files in self.clients.items()
                if (password := files.password()) is not None}

    def settings(self, user: str, url: str, **options: Any) -> NatsSettings:
        """:class:`NatsSettings` for ``user`` on ``url`` (its password, certificate, site)."""
        client = self._client(user)
        return NatsSettings.from_url(
            url, username=user, password=client.password(), ca_file=client.ca_file,
            cert_file=client.cert_file, key_file=client.key_file, site=self.site, **options)

    def mqtt_settings(self, user: str, host: str, port: int, **options: Any) -> MqttSettings:
        """:class:`MqttSettings` for ``user`` on a node's MQTT listener (MQTT 3.1.1)."""
        client = self._client(user)
        options.setdefault("protocol", "3.1.1")
        return MqttSettings(host=host, port=port, username=user, password=client.password(),
                            ca_file=client.ca_file, cert_file=client.cert_file,
                            key_file=client.key_file, **options)

    def _client(self, user: str) -> ClientFiles:
        if user not in self.clients:
            raise NatsSecurityError(f"no user {user!r} in {self.clients_directory}.")
        return self.clients[user]

    def to_dict(self) -> dict[str, Any]:
        return {
            "directory": str(self.directory),
            "roles": dict(self.roles),
            "site": self.site,
            "tls": self.tls,
            "clients_directory": str(self.clients_directory),
            "clients": {user: files.to_dict() for user, files in self.clients.items()},
            "ca_file": None if self.ca_file is None else str(self.ca_file),
            "ca_key_directory": None if self.ca_key_directory is None
            else str(self.ca_key_directory),
        }


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _conf(value: Any) -> str:
    """A permissions mapping in the server's configuration syntax."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key}: {_conf(item)}" for key, item in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_conf(item) for item in value) + "]"
    return _quote(str(value))


def write_nats_security(
    directory: str | os.PathLike,
    cameras: Sequence[str],
    matchers: Mapping[str, Sequence[int]],
    *,
    site: str | None = None,
    viewers: Sequence[str] = (VIEWER,),
    linkers: Sequence[str] = (),
    admin: str = ADMIN,
    tls: bool = True,
    hosts: Sequence[str] = ("127.0.0.1",),
    passwords: Mapping[str, str] | None = None,
    ca_directory: str | os.PathLike | None = None,
    clients_directory: str | os.PathLike | None = None,
) -> NatsSecurity:
    """Generate the users, permissions and TLS files of a secured NATS backbone.

    Args:
        directory: the servers' folder (``tls/`` goes there; nothing secret but the servers'
            own keys).
        cameras: camera ids.
        matchers: matcher id -> the planes it serves (see
            :func:`cblrs.runtime.broker.mosquitto_config.matcher_planes`).
        site: the site id of the subjects (see :class:`NatsSettings`).
        viewers: read-only logins (dashboards); on NATS a login may be shared.
        linkers: logins of ``cblrs linker``: every plane's tracks in (every plane a
            matcher serves, through the linker's consumers), the site's out.
        admin: the administrator's login (streams, consumers, buckets).
        tls: TLS with client certificates on the client and MQTT ports, and between nodes.
        hosts: the names or addresses the nodes are reached at (the servers' certificate).
        passwords: fixed passwords for some users (default: random).
        ca_directory: where the CAs' keys go (default ``<directory>-ca``).
        clients_directory: where the clients' folders go (default ``<directory>-clients``).

    Raises:
        NatsSecurityError: an unusable or repeated name, a plane out of range, a folder
            inside ``directory``, or a missing optional package.
    """
    directory = Path(directory).resolve()
    try:
        if site is not None:
            validate_site(site)
        for name in cameras:
            validate_client_id(name, "camera id")
        for name in [*matchers, *viewers, *linkers, admin]:
            validate_client_id(name, "user name")
    except (TransportError, CblrsError) as error:
        raise NatsSecurityError(str(error)) from None
    roles = {name: "camera" for name in cameras}
    roles.update({name: "matcher" for name in matchers})
    roles.update({name: "viewer" for name in viewers})
    roles.update({name: "linker" for name in linkers})
    roles[admin] = "admin"
    everyone = [*cameras, *matchers, *viewers, *linkers, admin]
    if len(roles) != len(everyone):
        raise NatsSecurityError(f"camera, matcher, viewer, linker and admin names must be "
                                f"distinct, got {everyone}.")
    for name, planes in matchers.items():
        if not planes or any(not 1 <= int(plane) <= 65535 for plane in planes):
            raise NatsSecurityError(f"matcher {name}: plane ids must be 1..65535, got "
                                    f"{list(planes)}.")
    try:
        clients_folder = check_outside(
            Path(clients_directory) if clients_directory is not None
            else default_side_folder(directory, "clients"), directory, "clients'")
        ca_keys = check_outside(
            Path(ca_directory) if ca_directory is not None
            else default_side_folder(directory, "ca"), directory, "CA's key")
        directory.mkdir(parents=True, exist_ok=True)
        chosen = dict(passwords or {})
        secret = {user: chosen.get(user) or new_password() for user in roles}
        site_planes = sorted({int(plane) for planes in matchers.values() for plane in planes})
        users = {
            user: (role, bcrypt_hash(secret[user]),
                   role_permissions(role, user, site_planes if role == "linker"
                                    else matchers.get(user, ()), site))
            for user, role in roles.items()
        }
        authority = route_authority = None
        files: dict[str, Path] = {}
        if tls:
            tls_directory = directory / "tls"
            authority = new_authority("cblrs NATS CA", tls_directory / "ca.crt", ca_keys)
            route_authority = new_authority("cblrs NATS route CA",
                                            tls_directory / "route-ca.crt", ca_keys)
            files = _server_files(tls_directory, authority, route_authority, hosts)
        clients = {user: write_client_folder(clients_folder, user, secret[user], authority)
                   for user in roles}
    except CredentialsError as error:
        raise NatsSecurityError(str(error)) from None
    return NatsSecurity(
        directory=directory, users=users, roles=roles, clients=clients,
        clients_directory=clients_folder, site=site, tls=tls,
        ca_file=authority.certificate_file if authority else None,
        server_cert_file=files.get("server_cert"), server_key_file=files.get("server_key"),
        route_ca_file=route_authority.certificate_file if route_authority else None,
        route_cert_file=files.get("route_cert"), route_key_file=files.get("route_key"),
        ca_key_directory=ca_keys if tls else None, hosts=tuple(hosts),
    )


def _server_files(directory: Path, authority: Authority, route_authority: Authority,
                  hosts: Sequence[str]) -> dict[str, Path]:
    """The servers' certificate and key, and the routes' (a node is a server and a client
    of its peers)."""
    certificate, key = issue_certificate(authority, "cblrs NATS server", server=True,
                                         client=False, hosts=hosts)
    route_certificate, route_key = issue_certificate(route_authority, "cblrs NATS route",
                                                     server=True, client=True, hosts=hosts)
    server_cert = directory / "server.crt"
    server_cert.write_bytes(certificate)
    route_cert = directory / "route.crt"
    route_cert.write_bytes(route_certificate)
    return {
        "server_cert": server_cert,
        "server_key": write_private(directory / "server.key", key),
        "route_cert": route_cert,
        "route_key": write_private(directory / "route.key", route_key),
    }
