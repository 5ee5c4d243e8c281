"""One matcher per plane: a lease held through a retained message on the broker.

Two matchers on one plane split its stream between two databases (with the same
credentials they also take the MQTT session from each other, many times a second). A
matcher therefore claims its plane before it acknowledges anything, and proves it holds the
claim for as long as it runs:

* the record is the retained message on ``cblrs/<plane>/lease``::

      {"schema": "cblrs.lease/1", "plane": 1, "matcher": "matcher1", "instance": "9f...",
       "state": "held", "heartbeat": 1763900000.5, "database": "1c...", "host": "edge-1",
       "pid": 4242}

* to read it, a matcher subscribes to the topic (the broker sends the retained record
  first) and publishes a non-retained *probe*; once its own probe comes back, the record
  seen before it is the current one;
* the plane is free when there is no record, the record says ``released`` (a clean stop),
  or its holder has not renewed it for ``ttl_s`` (a crash): a newcomer that finds a fresh
  record waits up to ``ttl_s`` (on its own clock, from when it read the record) for the
  holder's next heartbeat — any renewal the broker delivers, live or retained — and refuses
  if one comes;
* the holder renews the record every ``heartbeat_s``, checks it again after every
  reconnection, and steps down as soon as it sees another instance's claim;
* the record names the database (its ``database_id``): a matcher started under the same id
  (the same MQTT session) on another database than the one that served the plane last is
  refused unless allowed, because the messages its session acknowledged into that database
  are not in this one (a deleted file, a mistyped ``--db``).

The lease only works on a broker that keeps retained messages (any MQTT broker does; with
persistence they also survive a restart of the broker).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any, Literal

import msgspec

from cblrs.errors import CblrsError
from cblrs.runtime.transport.protocol import TransportError, reason_text, refused
from cblrs.runtime.transport.topics import lease_topic

logger = logging.getLogger(__name__)

LEASE_SCHEMA = "cblrs.lease/1"


class LeaseError(CblrsError):
    """The plane is held by another matcher, or was served from another database."""


class LeaseRecord(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """A ``cblrs.lease/1`` payload (see the module docstring); ``probe`` records are not
    retained and only mark a point in the broker's order of messages."""

    schema: str
    plane: int
    matcher: str
    instance: str
    state: Literal["held", "released", "probe"]
    heartbeat: float
    database: str = ""
    host: str = ""
    pid: int = 0
    nonce: str = ""

    def describe(self) -> str:
        where = f" on {self.host}" if self.host else ""
        pid = f" (pid {self.pid})" if self.pid else ""
        return f"matcher {self.matcher}{where}{pid}"


_decoder = msgspec.json.Decoder(LeaseRecord)


class _Retry(Exception):
    """A lease read that lost its connection or its answer: try again."""


class PlaneLease:
    """The lease of one matcher service on its plane.

    Args:
        transport: the service's transport (connected before :meth:`acquire`).
        plane_id: the plane.
        matcher_id: the matcher's id (its MQTT client id).
        database_id: the id of the service's database (:meth:`RuntimeStore.database_id`).
        allow_other_database: accept a plane last served from another database.
        heartbeat_s: how often the holder renews the record.
        ttl_s: a record not renewed for this long is free (a crashed holder).
        settle_s: after claiming, how long to watch for a competing claim.
        timeout_s: longest wait for the broker's answers.
        clock: wall clock (seconds since the Unix epoch).
    """

    def __init__(
        self,
        transport: Any,
        plane_id: int,
        matcher_id: str,
        database_id: str,
        *,
        allow_other_database: bool = False,
        heartbeat_s: float = 1.0,
        ttl_s: float = 4.0,
        settle_s: float = 0.1,
        timeout_s: float = 10.0,
        clock: Callable[[], float] = time.time,
    ):
        self.transport = transport
        self.plane_id = int(plane_id)
        self.matcher_id = matcher_id
        self.database_id = database_id
        self.allow_other_database = allow_other_database
        self.heartbeat_s = float(heartbeat_s)
        self.ttl_s = float(ttl_s)
        self.settle_s = float(settle_s)
        self.timeout_s = float(timeout_s)
        self.instance = uuid.uuid4().hex
        self.topic = lease_topic(self.plane_id)
        self._clock = clock
        self._host = socket.gethostname()
        self._pid = os.getpid()
        self._log: list[LeaseRecord] = []
        self._condition = threading.Condition()
        self._held = False
        self._lost: str | None = None
        self._on_lost: Callable[[str], None] | None = None
        self._on_checked: Callable[[], None] | None = None
        self._refused: str | None = None
        self._stop = threading.Event()
        self._recheck = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ---------------------------------------------------------------------------

    def register(self) -> None:
        """Subscribe to the lease topic (before the transport connects).

        At QoS 0: a matcher acknowledges no detections before it holds the lease, and a
        broker sends a client at most so many unacknowledged QoS 1 messages (Mosquitto's
        ``max_inflight_messages``), so QoS 1 lease records would wait behind a backlog of
        detections forever. QoS 0 deliveries are not held back; a record lost with a
        connection is read again after the reconnection.
        """
        self.transport.subscribe(self.topic, self._on_record, qos=0)

    @property
    def held(self) -> bool:
        """Whether this matcher holds the plane's lease now."""
        return self._held and self._lost is None

    def acquire(self) -> None:
        """Claim the plane, or raise.

        Raises:
            LeaseError: another instance holds the plane (it renewed its claim while we
                watched), or the plane was served from another database and that is not
                allowed. Nothing has been acknowledged when this is raised.
        """
        record = self._read()
        if record is not None and record.state == "held" and record.instance != self.instance:
            age = self._clock() - record.heartbeat
            if age < self.ttl_s:
                # Waited for on this matcher's own clock from now, not from the holder's
                # timestamp: a holder starved of CPU, or knocked off the broker by this very
                # matcher (same login, same session), renews late, not never.
                logger.warning(
                    "plane %d: the lease is held by %s (renewed %.1f s ago); waiting up to "
                    "%.0f s for its next renewal", self.plane_id, record.describe(),
                    max(age, 0.0), self.ttl_s)
                renewed = self._wait_for_renewal(record, self.ttl_s)
                if renewed is not None:
                    raise LeaseError(
                        f"plane {self.plane_id} is already served by {renewed.describe()} "
                        f"(database {renewed.database or 'unknown'}); stopping without "
                        "acknowledging anything (stop that matcher first, or give this one "
                        "another plane)."
                    )
            logger.warning("plane %d: the lease of %s expired (no renewal seen for %.0f s); "
                           "taking over", self.plane_id, record.describe(), self.ttl_s)
        if record is not None:
            self._check_database(record)
        self._claim()

    def start(
        self, on_lost: Callable[[str], None], on_checked: Callable[[], None] | None = None
    ) -> None:
        """Renew the claim every ``heartbeat_s`` in a thread; ``on_lost(reason)`` is called
        once if another instance claims the plane or the claim cannot be confirmed,
        ``on_checked()`` each time a :meth:`recheck` confirmed the claim."""
        self._on_lost = on_lost
        self._on_checked = on_checked
        self._thread = threading.Thread(
            target=self._renew, name=f"cblrs-lease-{self.plane_id}", daemon=True
        )
        self._thread.start()

    def recheck(self) -> None:
        """Check the claim again (call after a reconnection; the heartbeat thread does it)."""
        self._recheck.set()

    def wait_checked(self, timeout: float) -> bool:
        """After :meth:`recheck`: wait until the claim is confirmed; False if not in time."""
        deadline = time.monotonic() + timeout
        while self._recheck.is_set() and self._lost is None:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return self._lost is None

    def release(self) -> None:
        """Stop renewing and mark the record ``released`` (a restart may claim at once)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        if self._held and self._lost is None and getattr(self.transport, "connected", True):
            try:
                self._publish("released", retain=True)
            except Exception:  # a released lease still expires
                logger.warning("plane %d: could not release the lease", self.plane_id)
        self._held = False

    # -- internals ---------------------------------------------------------------------------

    def _on_record(self, delivery: Any) -> None:
        try:
            record = _decoder.decode(delivery.payload) if delivery.payload else None
        except (msgspec.DecodeError, msgspec.ValidationError):
            record = None
        delivery.ack()
        if record is None or record.schema != LEASE_SCHEMA or record.plane != self.plane_id:
            return
        with self._condition:
            self._log.append(record)
            self._condition.notify_all()
        if (self._held and record.state == "held" and record.instance != self.instance
                and self._lost is None):
            self._lose(f"{record.describe()} claimed plane {self.plane_id}")

    def _record(self, state: str, nonce: str = "") -> bytes:
        return msgspec.json.encode(LeaseRecord(
            LEASE_SCHEMA, self.plane_id, self.matcher_id, self.instance, state,  # type: ignore[arg-type]
            self._clock(), self.database_id, self._host, self._pid, nonce,
        ))

    def _publish(self, state: str, retain: bool, nonce: str = "") -> None:
        self.transport.publish(self.topic, self._record(state, nonce), qos=1, retain=retain,
                               on_result=self._on_result)

    def _on_result(self, reason: int) -> None:
        if refused(reason) and reason != -1:
            with self._condition:
                self._refused = reason_text(reason)
                self._condition.notify_all()

    def _check_refused(self) -> None:
        if self._refused is not None:
            raise LeaseError(
                f"the broker refused this matcher's lease message on {self.topic} "
                f"({self._refused}): log in with a matcher's credentials (a camera's or the "
                "viewer's may not serve a plane)."
            )

    def _read(self) -> LeaseRecord | None:
        """The current record: subscribe again (the broker re-sends the retained record),
        then wait for our own probe; the last claim before it is current.

        Retried while the connection comes and goes (another client with this matcher's id
        takes the session for a moment), up to ``timeout_s``.
        """
        deadline = time.monotonic() + self.timeout_s
        while True:
            self._check_refused()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LeaseError(
                    f"plane {self.plane_id}: the broker did not echo the lease probe on "
                    f"{self.topic} within {self.timeout_s:g} s; is this user allowed to "
                    "read and write it (a matcher's credentials)?"
                )
            if not getattr(self.transport, "connected", True):
                time.sleep(min(0.05, remaining))
                continue
            try:
                return self._read_once(min(2.0, remaining))
            except _Retry:
                continue

    def _read_once(self, timeout: float) -> LeaseRecord | None:
        with self._condition:
            start = len(self._log)
        resubscribe = getattr(self.transport, "resubscribe", None)
        try:
            if resubscribe is not None:
                resubscribe(self.topic)
            nonce = uuid.uuid4().hex
            self._publish("probe", retain=False, nonce=nonce)
        except TransportError:
            raise _Retry from None
        deadline = time.monotonic() + timeout
        with self._condition:
            while True:
                self._check_refused()
                seen = self._log[start:]
                for index, record in enumerate(seen):
                    if record.state == "probe" and record.nonce == nonce:
                        claims = [item for item in seen[:index] if item.state != "probe"]
                        return claims[-1] if claims else None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise _Retry
                self._condition.wait(min(remaining, 0.1))

    def _wait_for_renewal(self, record: LeaseRecord, seconds: float) -> LeaseRecord | None:
        """A newer claim of ``record``'s instance (or another instance's claim) within
        ``seconds``, or None (also when that instance released the plane).

        Decided from every record the broker delivers: renewals published while this matcher
        is connected, and the retained record the broker sends again on each re-subscription
        (asked for every ``heartbeat_s``; no probe round trip, which a connection that
        another client with this login keeps taking over may never complete). A client with
        this login taking this matcher's session over meanwhile is the holder alive too (two
        matchers with one login knock each other off the broker many times a second, and the
        holder's renewals may never reach this one): ``record`` is returned.
        """
        deadline = time.monotonic() + seconds
        next_ask = time.monotonic() + self.heartbeat_s
        takeovers = getattr(self.transport, "takeovers", 0)
        with self._condition:
            seen = len(self._log)
        while True:
            if getattr(self.transport, "takeovers", 0) > takeovers:
                logger.warning("plane %d: another client with this login took this matcher's "
                               "session over while it waited: %s is alive", self.plane_id,
                               record.describe())
                return record
            with self._condition:
                fresh, seen = self._log[seen:], len(self._log)
            for item in fresh:
                if item.state == "probe":
                    continue
                if item.instance == record.instance:
                    if item.state == "released":
                        return None
                    if item.heartbeat > record.heartbeat:
                        return item
                elif item.state == "held" and item.instance != self.instance:
                    return item
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._check_refused()
            resubscribe = getattr(self.transport, "resubscribe", None)
            if (resubscribe is not None and time.monotonic() >= next_ask
                    and getattr(self.transport, "connected", True)):
                next_ask = time.monotonic() + self.heartbeat_s
                try:
                    resubscribe(self.topic)
                except TransportError:
                    pass  # the connection went: asked again on the next round
            with self._condition:
                if len(self._log) == seen:
                    self._condition.wait(max(0.01, min(remaining, next_ask - time.monotonic())))

    def _check_database(self, record: LeaseRecord) -> None:
        # Only for the same matcher id, i.e. the same MQTT session: what that session's
        # broker queue handed over was acknowledged into the recorded database. Another id
        # has its own session (starting a plane afresh under a new id is a deliberate act).
        if (record.matcher == self.matcher_id and record.database
                and record.database != self.database_id and not self.allow_other_database):
            raise LeaseError(
                f"plane {self.plane_id} was last served by {record.describe()} from another "
                f"database (id {record.database}, not {self.database_id}): the messages it "
                "acknowledged are not in this one; restart with that database, or allow a new "
                "one (cblrs matcher --new-db)."
            )

    def _claim(self) -> None:
        with self._condition:
            start = len(self._log)
        self._publish("held", retain=True)
        deadline = time.monotonic() + self.timeout_s
        with self._condition:
            while not any(item.instance == self.instance and item.state == "held"
                          for item in self._log[start:]):
                self._check_refused()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise LeaseError(
                        f"plane {self.plane_id}: the broker did not confirm the lease claim on "
                        f"{self.topic} within {self.timeout_s:g} s; is this user allowed to "
                        "write it (a matcher's credentials)?"
                    )
                self._condition.wait(remaining)
        time.sleep(self.settle_s)
        with self._condition:
            after = self._log[start:]
        mine = max(index for index, item in enumerate(after)
                   if item.instance == self.instance and item.state == "held")
        rivals = [item for item in after[mine + 1:]
                  if item.state == "held" and item.instance != self.instance]
        if rivals:
            raise LeaseError(
                f"plane {self.plane_id} was claimed at the same moment by "
                f"{rivals[-1].describe()}; stopping without acknowledging anything."
            )
        self._held = True
        logger.info("plane %d: lease held by %s (instance %s)", self.plane_id,
                    self.matcher_id, self.instance[:8])

    def _renew(self) -> None:
        while not self._stop.wait(0.0 if self._recheck.is_set() else self.heartbeat_s):
            if self._lost is not None:
                return
            try:
                if self._recheck.is_set():
                    if not getattr(self.transport, "connected", True):
                        time.sleep(0.05)
                        continue
                    record = self._read()
                    if record is not None and record.state == "held" and (
                            record.instance != self.instance):
                        self._lose(f"{record.describe()} holds plane {self.plane_id} now")
                        return
                    self._publish("held", retain=True)
                    self._recheck.clear()
                    if self._on_checked is not None:
                        self._on_checked()
                    continue
                self._publish("held", retain=True)
            except Exception as error:  # the broker went away: checked after reconnecting
                if getattr(self.transport, "connected", True):
                    self._lose(f"the lease could not be renewed: {error}")
                    return

    def _lose(self, reason: str) -> None:
        if self._lost is not None:
            return
        self._lost = reason
        self._recheck.clear()
        logger.error("plane %d: lease lost: %s; this matcher stops acknowledging",
                     self.plane_id, reason)
        if self._on_lost is not None:
            self._on_lost(reason)
