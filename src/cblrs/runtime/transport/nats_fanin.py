"""Several planes' durable NATS consumers behind one transport: how the linker reads tracks.

A :class:`~cblrs.runtime.transport.nats_transport.NatsTransport` serves one durable consumer
on one stream, and every plane has its own tracks stream (``CBLRS_P<plane>_TRACKS``). The
site's linker reads every plane's track updates, so :class:`NatsFanIn` holds one
``NatsTransport`` per plane, each with the linker's durable consumer on that plane's tracks
stream (:func:`linker_consumer`: one per linker name, and per site since the streams are),
and one more connection that publishes the linker's outputs and reads anything else. To the
service it is one :class:`~cblrs.runtime.transport.protocol.Transport`: ``delivery.ack()``
acknowledges on the plane's own consumer, so a linker killed at any moment gets again, from
each plane's stream, every update it had not acknowledged (it acknowledges after its SQLite
commit), and the updates published while it was down are kept by the streams (their
``retention_s``, 7 days by default) until it comes back.

Who creates the consumers: a client that manages streams (no users on the servers, or the
admin's login with ``manage=True``: ``cblrs linker --prepare``); a linker's own login may only
read, pull, acknowledge and reset its consumers (:mod:`cblrs.runtime.broker.nats_auth`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cblrs.runtime.transport.nats_settings import NatsSettings
from cblrs.runtime.transport.nats_subjects import _classify, site_subject
from cblrs.runtime.transport.nats_transport import NatsTransport
from cblrs.runtime.transport.protocol import Handler, Will
from cblrs.runtime.transport.topics import validate_client_id

LINKER_CONSUMER_PREFIX = "cblrs-linker-"


def linker_consumer(linker_id: str) -> str:
    """The durable consumer of linker ``linker_id`` on each plane's tracks stream.

    ``cblrs-linker-<id>``, where the id's ``_`` is written ``__`` and its ``.`` (which a
    consumer name may not hold) ``_d``, so two linker ids never share a consumer.

    Raises:
        TopicError: ``linker_id`` is not a usable client id.
    """
    validate_client_id(linker_id, "linker id")
    return LINKER_CONSUMER_PREFIX + linker_id.replace("_", "__").replace(".", "_d")


class NatsFanIn:
    """The track updates of several planes through their durable consumers, and one
    publisher (see the module).

    Args:
        client_id: the connection name; the planes' connections are ``<client_id>-p<plane>``.
        settings: servers, login, site.
        durable: the consumer's name on every plane's tracks stream (:func:`linker_consumer`).
        planes: the planes whose tracks are read.
        replay: on connect, every consumer delivers its stream from the first message again
            (a linker rebuilding an empty database).
        will: published on a clean close.
    """

    def __init__(
        self,
        client_id: str,
        settings: NatsSettings,
        *,
        durable: str,
        planes: Sequence[int],
        replay: bool = False,
        will: Will | None = None,
    ):
        if not planes:
            raise ValueError("NatsFanIn needs at least one plane.")
        self.client_id = client_id
        self.settings = settings
        self.publisher = NatsTransport(client_id, settings, will=will)
        self.planes = {
            int(plane): NatsTransport(
                f"{client_id}-p{int(plane)}",
                settings,
                durable=durable,
                replay=replay,
                consume="tracks",
            )
            for plane in sorted(set(planes))
        }

    @property
    def connected(self) -> bool:
        """Whether every connection is up now."""
        return self.publisher.connected and all(
            transport.connected for transport in self.planes.values()
        )

    @property
    def caught_up(self) -> bool:
        """Whether every plane's consumer has delivered everything its stream holds."""
        return all(transport.caught_up for transport in self.planes.values())

    @property
    def refused_subscriptions(self) -> list[str]:
        return [
            subject
            for transport in (self.publisher, *self.planes.values())
            for subject in transport.refused_subscriptions
        ]

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """A plane's tracks go to that plane's consumer, anything else to the publisher's
        plain subscriptions."""
        subject = site_subject(topic_filter, self.settings.site)
        kind = _classify(subject, self.settings.site)
        if kind is not None and kind[0] == "tracks" and kind[1] in self.planes:
            self.planes[kind[1]].subscribe(topic_filter, handler, qos)
        else:
            self.publisher.subscribe(topic_filter, handler, qos)

    def open(self) -> None:
        """Connect the publisher (so a refused login is said once, before any consumer)."""
        self.publisher.open()

    def connect(self, wait: bool = True) -> None:
        """Connect every plane's consumer, then the publisher's subscriptions.

        Raises:
            TransportError: a server refused or could not be reached, or a consumer is
                missing or not this login's (the connections made are closed again).
        """
        started: list[NatsTransport] = []
        try:
            self.publisher.open()
            for transport in self.planes.values():
                transport.connect(wait)
                started.append(transport)
            self.publisher.connect(wait)
        except BaseException:
            for transport in started:
                transport.close(unclean=True, timeout=1.0)
            self.publisher.close(unclean=True, timeout=1.0)
            raise

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> None:
        self.publisher.publish(topic, payload, qos, retain)

    def flush(self, timeout: float) -> bool:
        return self.publisher.flush(timeout)

    def pending(self) -> int:
        return self.publisher.pending()

    def close(self, unclean: bool = False, timeout: float = 5.0) -> None:
        """Close the planes' connections (their queued acknowledgements go first), then the
        publisher's (which publishes the will on a clean close)."""
        for transport in self.planes.values():
            transport.close(unclean=unclean, timeout=timeout)
        self.publisher.close(unclean=unclean, timeout=timeout)

    def call(self, coroutine: Any, timeout: float | None = 30.0) -> Any:
        """Run a coroutine on the publisher's event loop (see :meth:`NatsTransport.call`)."""
        return self.publisher.call(coroutine, timeout)

    @property
    def jetstream(self) -> Any:
        return self.publisher.jetstream
