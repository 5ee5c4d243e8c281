"""The plane lease on an MQTT-like backbone (the in-process broker): who may serve a plane."""

from __future__ import annotations

import threading

import pytest

from cblrs.runtime.matcher.lease import LeaseError, PlaneLease
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport


def _lease(broker, client_id: str, database_id: str) -> PlaneLease:
    transport = InProcessTransport(broker, client_id)
    lease = PlaneLease(transport, 1, "matcher1", database_id, ttl_s=1.5, timeout_s=5.0)
    lease.register()
    transport.connect()
    return lease


def test_a_session_taken_over_while_waiting_means_the_holder_is_alive():
    """Two matchers with one login knock each other off the broker many times a second, so
    the holder's renewals may never reach the newcomer (seen under load: it concluded the lease
    had expired). The take-over of its own session is the holder alive: refused as served."""
    broker = InProcessBroker()
    holder = _lease(broker, "matcher1-a", "database-a")
    holder.acquire()  # claimed; no renewal thread, so no renewal ever comes
    newcomer = _lease(broker, "matcher1-b", "database-a")
    taken = threading.Timer(0.3, lambda: setattr(newcomer.transport, "takeovers", 1))
    taken.start()
    with pytest.raises(LeaseError, match=r"plane 1 is already served by matcher matcher1"):
        newcomer.acquire()
    taken.join()


def test_without_a_take_over_a_silent_holder_expires():
    """The same wait with nobody taking the session: the silent holder's lease expires and
    the newcomer (same database) takes the plane."""
    broker = InProcessBroker()
    holder = _lease(broker, "matcher1-a", "database-a")
    holder.acquire()
    newcomer = _lease(broker, "matcher1-b", "database-a")
    newcomer.acquire()
    assert newcomer._held
