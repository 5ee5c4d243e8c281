"""How many connections the dashboard holds, and for how long before a request arrives.

uvicorn keeps a connection that has sent part of a request, or nothing, for as long as the
client keeps it open: its keep-alive time-out starts only after a response, and any byte
stops it. So anyone who reaches the port (no login needed) could hold connections until the
process runs out of file descriptors (1024 by default under systemd and in most shells),
and then nobody got a page; measured here, 1,100 connections sending a header line every 3 s
kept ``/healthz`` from answering for as long as they lasted, and each refused ``accept()``
wrote a traceback to the log (89,000 lines in 10 s).

:func:`guarded_protocol` is uvicorn's h11 protocol with three limits:

* a connection must send a whole request (headers and body; bodies are at most 1 MiB)
  within ``request_timeout_s`` of opening or of its previous response, else it is closed;
  once a request has arrived, answering it may take as long as it takes (a live stream);
* one address holds at most ``per_address`` connections, and the server at most
  ``max_connections`` (by default what the process's open-files limit leaves, see
  :func:`connection_budget`, so ``accept()`` never fails): past either, a new connection
  closes the oldest one of that address (of the server) that is still waiting for its
  request, so a client holding half-sent requests loses them to the next client, also one
  on the same address (every local client is 127.0.0.1); when none is waiting (each is
  answering a request, e.g. live streams), the new connection is closed at once.

Each is counted (``stats``: ``slow``, ``evicted``, ``refused``); a refusal is logged.

With TLS, asyncio hands a connection to the protocol only once its handshake is done, so
these limits start there; :func:`serve` runs uvicorn on an event loop that gives a handshake
(and the closing exchange) :data:`TLS_HANDSHAKE_TIMEOUT_S` instead of asyncio's 60 s.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from collections import Counter
from typing import Any, ClassVar

logger = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 20.0
PER_ADDRESS = 64
RESERVED_FILES = 128
"""File descriptors kept for what is not a connection: databases, the site file, logs."""
MAX_CONNECTIONS = 16_384
TLS_HANDSHAKE_TIMEOUT_S = 5.0
"""With TLS, the seconds a connection has to finish its handshake (and to close it again):
until then the limits below do not see it (asyncio hands it to the protocol once the
handshake is done), and asyncio's default would hold it for 60 s."""


def raise_open_files_limit() -> int:
    """Raise this process's soft limit of open files to its hard limit; the new soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (OSError, ValueError):  # not allowed here: keep the soft limit
            pass
    return soft


def connection_budget() -> int:
    """The connections this process may hold: its open-files limit less
    :data:`RESERVED_FILES`, at least 16 and at most :data:`MAX_CONNECTIONS`."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return MAX_CONNECTIONS
    return max(16, min(MAX_CONNECTIONS, soft - RESERVED_FILES))


def guarded_protocol(
    request_timeout_s: float = REQUEST_TIMEOUT_S,
    per_address: int = PER_ADDRESS,
    max_connections: int | None = None,
) -> type:
    """uvicorn's h11 protocol class with the limits of this module (pass it as
    ``uvicorn.Config(http=...)``); its ``stats`` count ``slow``, ``evicted`` and ``refused``
    connections."""
    import h11  # optional extra: pip install cblrs[dashboard]
    from uvicorn.protocols.http.h11_impl import H11Protocol

    limit = connection_budget() if max_connections is None else max_connections
    by_address: dict[str, dict[Any, None]] = {}  # address -> its connections, oldest first
    every: dict[Any, None] = {}  # every connection, oldest first
    waiting = (h11.IDLE, h11.SEND_BODY)  # no request yet, or its body still on its way

    class GuardedH11Protocol(H11Protocol):
        stats: ClassVar[Counter[str]] = Counter()

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._deadline: Any = None
            self._address = self.client[0] if self.client else "?"
            own = by_address.setdefault(self._address, {})
            own[self] = None
            every[self] = None
            for group, most in ((own, per_address), (every, limit)):
                if len(group) > most and not self._make_room(group):
                    self.stats["refused"] += 1
                    if (
                        self.stats["refused"] in (1, 10, 100, 1000)
                        or self.stats["refused"] % 10_000 == 0
                    ):  # never a log flood
                        logger.warning(
                            "dashboard: closed a connection from %s at once: %d "
                            "connections are answering requests (at most %d per "
                            "address, %d in all; %d refused so far)",
                            self._address,
                            len(group) - 1,
                            per_address,
                            limit,
                            self.stats["refused"],
                        )
                    self._forget()
                    transport.abort()
                    return
            self._arm()

        def _make_room(self, group: dict[Any, None]) -> bool:
            """Close the oldest connection of ``group`` still waiting for a request."""
            for other in group:
                if other is not self and other.conn.their_state in waiting:
                    self.stats["evicted"] += 1
                    other._forget()
                    other.transport.abort()
                    return True
            return False

        def _forget(self) -> None:
            self._disarm()
            every.pop(self, None)
            own = by_address.get(self._address, {})
            own.pop(self, None)
            if not own:
                by_address.pop(self._address, None)

        def _arm(self) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(request_timeout_s, self._too_slow)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _too_slow(self) -> None:
            self._deadline = None
            if self.conn.their_state in waiting and not self.transport.is_closing():
                self.stats["slow"] += 1
                self.transport.abort()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state not in waiting:  # the whole request has arrived
                self._disarm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing() and self.conn.their_state in waiting:
                self._arm()  # the next request, in time too

        def connection_lost(self, exc: Exception | None) -> None:
            self._forget()
            super().connection_lost(exc)

    return GuardedH11Protocol


class BoundedHandshakeLoop(asyncio.SelectorEventLoop):
    """asyncio's event loop whose servers give a TLS handshake, and a TLS connection's
    closing exchange, :data:`TLS_HANDSHAKE_TIMEOUT_S` (uvicorn passes neither)."""

    async def create_server(self, *args: Any, **kwargs: Any) -> Any:
        if kwargs.get("ssl") is not None:
            kwargs.setdefault("ssl_handshake_timeout", TLS_HANDSHAKE_TIMEOUT_S)
            kwargs.setdefault("ssl_shutdown_timeout", TLS_HANDSHAKE_TIMEOUT_S)
        return await super().create_server(*args, **kwargs)


def serve(server: Any, sockets: list[Any]) -> None:
    """Run the uvicorn ``server`` on ``sockets`` until it stops, as ``server.run`` does, on a
    :class:`BoundedHandshakeLoop`."""
    with asyncio.Runner(loop_factory=BoundedHandshakeLoop) as runner:
        runner.run(server.serve(sockets=sockets))
