"""The site's alert rules, run by the matcher service: observed, committed, published, posted.

:class:`AlertService` is the part of :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`
that watches the plane for the rules of the site file's ``alerts:`` section
(:mod:`cblrs.alerts`). It runs in the service's process, never in the tracker's, with threads
of its own, so an alert (a slow webhook, a broker outage) never delays tracking:

* the **alerts** thread, every ``interval_s`` (1 s): builds an
  :class:`~cblrs.alerts.Observation` of the plane (:meth:`AlertService.observation`: the
  zones' occupancy and longest open visit from the tracker process's live state, the line
  crossings committed since the last observation from the events table, each camera's
  silence and status as the service received them, the tracker's lag), feeds it to the
  :class:`~cblrs.alerts.AlertLedger` — the episodes' new state, the alerts they cause and how
  far the events table was read are committed in one transaction of the matcher's SQLite
  file — and publishes on ``cblrs/<plane>/alerts`` (QoS 1, retained) every alert the broker
  has not acknowledged yet, in order, marking each once it has (the ledger's outbox, under
  the name :data:`BACKBONE`);
* one **webhook** thread per webhook: posts, in order, what that webhook has not
  acknowledged (HMAC-signed, time-outs, retries with back-off: :mod:`cblrs.alerts.webhook`).

Time is the service's wall clock (seconds since 1970): a camera that went silent has no
capture time to advance, and line crossings count from when the matcher committed them. A
matcher killed at any moment restarts from what it committed: an open episode is neither
fired again nor forgotten (its "cleared" comes once), crossings are counted once, and an
alert committed but not yet published or posted is sent after the restart (receivers
de-duplicate on ``(episode, state)``: an acknowledgement lost in a crash means a second
delivery).
"""

from __future__ import annotations

import inspect
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from cblrs.alerts import AlertLedger, AlertsModel, Delivery, Observation, WebhookSender
from cblrs.alerts.rules import AlertsError, LineCountRule
from cblrs.alerts.webhook import read_secret
from cblrs.runtime.outputs.events import encode_alert
from cblrs.runtime.transport.topics import alerts_topic

logger = logging.getLogger(__name__)

BACKBONE = "cblrs/backbone"
"""The ledger's name for the broker (``alerts.delivered``); no webhook may take it."""
EVENTS_SEEN_KEY = "alert_events_seen"
"""The ``meta`` key: the last ``events.id`` the alerts have counted crossings from."""
ACK_TIMEOUT_S = 10.0


def make_senders(alerts: AlertsModel, folder: Path | None = None,
                 environment: dict[str, str] | None = None) -> dict[str, WebhookSender]:
    """One sender per webhook, with its secret read now (a missing or readable-by-others
    secret stops the matcher before it starts, with one sentence).

    Raises:
        AlertsError: a secret cannot be read, or a webhook is named :data:`BACKBONE`.
    """
    senders = {}
    for webhook in alerts.webhooks:
        if webhook.name == BACKBONE:
            raise AlertsError(f"webhook {BACKBONE!r}: that name is the broker's; rename it.")
        senders[webhook.name] = WebhookSender(webhook, read_secret(webhook, folder, environment))
    return senders


def site_alerts(site: Any) -> tuple[AlertsModel | None, dict[str, WebhookSender]]:
    """A site's alerts for the matcher (None without rules) and their webhooks' senders.

    Raises:
        AlertsError: see :func:`make_senders`.
    """
    if site is None or not site.alerts.rules:
        return None, {}
    folder = site.path.parent if site.path is not None else None
    return site.alerts, make_senders(site.alerts, folder)


class _Backbone:
    """The broker as an outbox destination: publish, wait for the acknowledgement."""

    def __init__(self, transport: Any, plane_id: int, active: Callable[[], list[dict]]):
        self.transport = transport
        self.plane_id = plane_id
        self.topic = alerts_topic(plane_id)
        self._active = active
        try:
            self._with_result = "on_result" in inspect.signature(transport.publish).parameters
        except (TypeError, ValueError):
            self._with_result = False

    def send(self, body: dict[str, Any]) -> Delivery:
        if not getattr(self.transport, "connected", True):
            return Delivery(False, 0, None, "not connected to the broker")
        payload = encode_alert(body, self.plane_id, self._active())
        if not self._with_result:
            self.transport.publish(self.topic, payload, qos=1, retain=True)
            done = bool(self.transport.flush(ACK_TIMEOUT_S))
            return Delivery(done, 1, None, None if done else "not acknowledged")
        answered = threading.Event()
        reasons: list[int] = []

        def on_result(reason: int) -> None:
            reasons.append(reason)
            answered.set()

        self.transport.publish(self.topic, payload, qos=1, retain=True, on_result=on_result)
        if not answered.wait(ACK_TIMEOUT_S):
            return Delivery(False, 1, None, "not acknowledged")
        ok = 0 <= reasons[0] < 0x80
        return Delivery(ok, 1, reasons[0], None if ok else f"refused (reason {reasons[0]})")


class AlertService:
    """The alert rules of one plane, run in the matcher service (see the module docstring).

    Args:
        transport: the service's transport.
        store: the service's store (its connection in the service's process).
        plane_id: the plane.
        camera_ids: its cameras.
        alerts: the site's ``alerts:`` section.
        senders: webhook name -> sender (:func:`make_senders`).
        reporter: the service's :class:`~cblrs.runtime.outputs.analytics_service.ServiceReporter`
            (live state, camera health).
        lag: ``lag(now)``: how far tracking is behind ``now``, seconds (None: unknown).
        interval_s: seconds between observations.
        wall_clock: seconds since 1970.
        calendar: the site's opening hours (:class:`cblrs.localtime.LocalCalendar`): the
            places' rules are quiet while it is closed (None: always open).
    """

    def __init__(
        self,
        transport: Any,
        store: Any,
        plane_id: int,
        camera_ids: list[str],
        alerts: AlertsModel,
        senders: Mapping[str, WebhookSender],
        reporter: Any,
        lag: Callable[[float], float | None],
        *,
        interval_s: float = 1.0,
        wall_clock: Callable[[], float] = time.time,
        calendar: Any = None,
    ):
        self.calendar = calendar
        self.transport = transport
        self.store = store
        self.plane_id = int(plane_id)
        self.camera_ids = list(camera_ids)
        self.alerts = alerts
        self.senders = dict(senders)
        self.reporter = reporter
        self.lag = lag
        self.interval_s = float(interval_s)
        self._wall_clock = wall_clock
        self._counts_lines = any(isinstance(rule, LineCountRule) for rule in alerts.rules)
        self.ledger: AlertLedger | None = None
        self._backbone = _Backbone(transport, self.plane_id, self._active)
        self._events_seen = 0
        self._stop = threading.Event()
        self._wakes = {name: threading.Event() for name in self.senders}
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self.failures = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the ledger (resuming its episodes) and start the threads."""
        self.ledger = AlertLedger(self.store, self.alerts, {"plane": self.plane_id},
                                  calendar=self.calendar)
        seen = self.store.get_meta(EVENTS_SEEN_KEY)
        if seen is None:  # counting starts now, not from the history already in the file
            seen = self._last_event_id()
        self._events_seen = int(seen)
        self._threads = [threading.Thread(target=self._observe_loop, daemon=True,
                                          name=f"cblrs-alerts-{self.plane_id}")]
        self._threads += [
            threading.Thread(target=self._deliver_loop, args=(name,), daemon=True,
                             name=f"cblrs-webhook-{self.plane_id}-{name}")
            for name in self.senders
        ]
        for thread in self._threads:
            thread.start()
        logger.info("plane %d: %d alert rules, webhooks: %s", self.plane_id,
                    len(self.alerts.rules), ", ".join(self.senders) or "none")

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the threads (what is not delivered stays in the outbox for the next run)."""
        self._stop.set()
        for sender in self.senders.values():
            sender.close(0.0)
        for wake in self._wakes.values():
            wake.set()
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))

    # ------------------------------------------------------------------ observation
    def observation(self, now: float) -> tuple[Observation, int]:
        """The plane at ``now`` and the last events row it counted crossings from."""
        live = self.reporter.live_state()
        longest: dict[str, float] = {}
        for zone, _, seconds in live.get("dwell", []):
            longest[zone] = max(longest.get(zone, 0.0), float(seconds))
        crossings: list[tuple[str, str, float]] = []
        seen = self._events_seen
        if self._counts_lines and self.store.has_table("events"):
            rows = self.store.query(
                "SELECT id, place, body FROM events WHERE id > ? AND kind = 'line_crossed' "
                "ORDER BY id", (seen,))
            for identifier, place, body in rows:
                direction = json.loads(body).get("direction")
                if direction in ("positive", "negative"):
                    crossings.append((place, direction, now))
                seen = max(seen, int(identifier))
        silence: dict[str, float | None] = dict.fromkeys(self.camera_ids)
        offline: set[str] = set()
        for row in self.reporter.health.summary():
            if row["camera"] in silence:
                silence[row["camera"]] = row["last_age_s"]
                if not row["online"]:
                    offline.add(row["camera"])
        observation = Observation(
            timestamp=now,
            occupancy={zone: int(count) for zone, count in live.get("occupancy", {}).items()},
            longest_visit_s=longest,
            crossings=tuple(crossings),
            camera_silence_s=silence,
            cameras_offline=frozenset(offline),
            lag_s=self.lag(now),
        )
        return observation, seen

    def observe_once(self) -> int:
        """Observe, commit, publish what the broker has not acknowledged; alerts caused."""
        assert self.ledger is not None
        observation, seen = self.observation(self._wall_clock())
        with self._lock:
            events = self.ledger.observe(observation, {EVENTS_SEEN_KEY: seen})
            self._events_seen = seen
        for event in events:
            logger.warning("plane %d: alert %s %s (%s %s: %g, threshold %g)", self.plane_id,
                           event.episode, event.state, event.kind, event.subject, event.value,
                           event.threshold)
        self.ledger.deliver({BACKBONE: self._backbone})
        if events:
            for wake in self._wakes.values():
                wake.set()
        return len(events)

    def active(self) -> list[dict[str, Any]]:
        """The episodes firing now."""
        return self._active()

    def _active(self) -> list[dict[str, Any]]:
        if self.ledger is None:
            return []
        with self._lock:
            return self.ledger.episodes.active()

    def _last_event_id(self) -> int:
        if not self.store.has_table("events"):
            return 0
        ((last,),) = self.store.query("SELECT COALESCE(MAX(id), 0) FROM events")
        return int(last)

    # ------------------------------------------------------------------ threads
    def _observe_loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.observe_once()
            except Exception:  # alerts must never stop the matcher; the next tick retries
                self.failures += 1
                logger.exception("plane %d: evaluating alerts failed", self.plane_id)

    def _deliver_loop(self, name: str) -> None:
        assert self.ledger is not None
        sender, wake = self.senders[name], self._wakes[name]
        webhook = sender.webhook
        while not self._stop.is_set():
            pause = self.interval_s
            try:
                pending = self._undelivered(name)
                if pending and self.ledger.deliver({name: sender}) < min(pending, 100):
                    # It has retried with back-off already: wait before the next round.
                    pause = min(webhook.max_backoff_s,
                                webhook.backoff_s * 2 ** webhook.retries)
            except Exception:
                logger.exception("plane %d: webhook %s: delivery failed", self.plane_id, name)
            wake.wait(pause)
            wake.clear()

    def _undelivered(self, name: str) -> int:
        ((count,),) = self.store.query(
            "SELECT COUNT(*) FROM alerts WHERE instr(delivered, ?) = 0", (json.dumps(name),))
        return int(count)
