"""Fixtures for runtime tests: real Mosquitto brokers on free loopback ports, and transports.

Every broker here is started by the test session itself with its own configuration in a
temporary folder; the system broker (port 1883) is never used.

Fixtures:
    mosquitto: module-scoped anonymous broker with persistence (``RunningBroker``).
    mosquitto_auth: module-scoped broker with users CVLab1, CVLab2 (cameras), matcher1,
        matcher2 (matchers for planes 1 and 2), viewer; password file and ACL.
    mosquitto_tls: like ``mosquitto_auth`` with a TLS-only listener (client certificates).
    start_mosquitto: factory ``start_mosquitto(cameras=(), matchers=(), **options)`` for a
        broker owned by one test (stopped at the end); options go to write_broker_config.
    inprocess_broker: a fresh InProcessBroker.
    transport_kind: "inprocess" or "mqtt" (parametrized).
    make_transport: factory ``make_transport(name, *, persistent=True, will=None, user=None)``
        returning an unconnected transport of ``transport_kind``; the same ``name`` within
        one test gives the same client id; all are closed at teardown.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest
from broker_user import RUN_AS
from fault_plant import fault_references, plant  # noqa: F401 (fixtures of the fault tests)

from cblrs.runtime.broker.mosquitto_config import (
    BrokerFiles,
    MosquittoProcess,
    find_mosquitto,
    free_port,
    write_broker_config,
)
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.protocol import Transport, Will

TEST_CAMERAS = ("CVLab1", "CVLab2")
TEST_MATCHERS = ("matcher1", "matcher2")
TEST_PLANES = (1, 2)
FAST = {
    "connect_timeout_s": 3.0,
    "reconnect_min_s": 0.05,
    "reconnect_max_s": 0.5,
    "keepalive_s": 10,
}
"""Client options that keep tests short: quick reconnection, bounded waits."""

_unique = itertools.count()


def mosquitto_available() -> bool:
    return find_mosquitto() is not None


def require_mosquitto() -> None:
    if not mosquitto_available():
        pytest.skip("mosquitto not installed")





@dataclass
class RunningBroker:
    """A started Mosquitto with the files that configure it."""

    files: BrokerFiles
    process: MosquittoProcess

    @property
    def port(self) -> int:
        return self.files.port

    def settings(self, user: str | None = None, **options) -> MqttSettings:
        """Client settings for ``user`` (None: anonymous), with the fast test timeouts."""
        return self.files.settings(user, **{**FAST, **options})

    def restart(self) -> None:
        self.process.restart()

    def stop(self) -> None:
        self.process.stop()

    def start(self) -> None:
        self.process.start()


def _start(directory, cameras, matchers, **options) -> RunningBroker:
    require_mosquitto()
    options.setdefault("plane_ids", TEST_PLANES)
    options.setdefault("run_as", RUN_AS)
    files = write_broker_config(
        directory, list(cameras), list(matchers), port=free_port(), **options
    )
    process = MosquittoProcess.from_files(files)
    process.start()
    return RunningBroker(files, process)


@pytest.fixture(scope="module")
def mosquitto(tmp_path_factory) -> Iterator[RunningBroker]:
    directory = tmp_path_factory.mktemp("mosquitto")
    broker = _start(directory, (), (), allow_anonymous=True, viewer=False)
    yield broker
    broker.stop()


@pytest.fixture(scope="module")
def mosquitto_auth(tmp_path_factory) -> Iterator[RunningBroker]:
    broker = _start(tmp_path_factory.mktemp("mosquitto-auth"), TEST_CAMERAS, TEST_MATCHERS)
    yield broker
    broker.stop()


@pytest.fixture(scope="module")
def mosquitto_tls(tmp_path_factory) -> Iterator[RunningBroker]:
    broker = _start(tmp_path_factory.mktemp("mosquitto-tls"), TEST_CAMERAS, TEST_MATCHERS, tls=True)
    yield broker
    broker.stop()


@pytest.fixture
def start_mosquitto(tmp_path) -> Iterator[Callable[..., RunningBroker]]:
    started: list[RunningBroker] = []

    def start(cameras=(), matchers=(), **options) -> RunningBroker:
        if not cameras and not matchers:
            options.setdefault("allow_anonymous", True)
            options.setdefault("viewer", False)
        broker = _start(tmp_path / f"broker{len(started)}", cameras, matchers, **options)
        started.append(broker)
        return broker

    yield start
    for broker in started:
        broker.stop()


@pytest.fixture
def inprocess_broker() -> InProcessBroker:
    return InProcessBroker()


@pytest.fixture(params=["inprocess", "mqtt"])
def transport_kind(request) -> str:
    if request.param == "mqtt":
        require_mosquitto()
    return request.param


@pytest.fixture
def make_transport(transport_kind, request) -> Iterator[Callable[..., Transport]]:
    """Unconnected transports of the parametrized kind, closed at teardown."""
    created: list[Transport] = []
    token = f"t{next(_unique)}"
    if transport_kind == "mqtt":
        broker: RunningBroker = request.getfixturevalue("mosquitto")
    else:
        shared = InProcessBroker()

    def make(
        name: str,
        *,
        persistent: bool = True,
        will: Will | None = None,
        settings: MqttSettings | None = None,
    ) -> Transport:
        client_id = f"{token}-{name}"
        transport: Transport
        if transport_kind == "mqtt":
            transport = MqttTransport(
                client_id, settings or broker.settings(), persistent=persistent, will=will
            )
        else:
            transport = InProcessTransport(shared, client_id, persistent=persistent, will=will)
        created.append(transport)
        return transport

    yield make
    for transport in created:
        try:
            transport.close(timeout=0.5)
        except Exception:  # a test may have closed it or stopped the broker already
            pass
