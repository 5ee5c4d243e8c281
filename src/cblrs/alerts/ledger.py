"""Alert episodes kept in the matcher's SQLite file: fired once, cleared once, delivered once.

:class:`AlertLedger` runs :class:`~cblrs.alerts.episodes.AlertEpisodes` on a store
(:class:`cblrs.runtime.matcher.store.RuntimeStore`, or any object with ``write``, ``query`` and
``get_meta``): each observation's events and the episodes' new state are committed in one
transaction, so a matcher killed at any moment restarts with the episodes it had committed —
an open episode is not fired again, and its "cleared" comes once. The ``alerts`` table is also
the webhooks' outbox: each row records the webhooks that answered 2xx, and
:meth:`AlertLedger.deliver` sends, in order, what each webhook has not acknowledged yet (a
webhook that fails keeps its rows for the next call; receivers de-duplicate on the episode
header, since an answer lost in transit means a second delivery).
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Mapping
from typing import Any

from cblrs.alerts.episodes import AlertEpisodes, AlertEvent, Observation
from cblrs.alerts.rules import AlertsModel
from cblrs.alerts.webhook import WebhookSender

logger = logging.getLogger(__name__)

ALERTS_SCHEMA = """
CREATE TABLE IF NOT EXISTS alerts (
    id INTEGER PRIMARY KEY,
    episode TEXT NOT NULL,
    state TEXT NOT NULL,
    timestamp REAL NOT NULL,
    body TEXT NOT NULL,
    delivered TEXT NOT NULL DEFAULT '[]',
    UNIQUE (episode, state)
);
"""
STATE_KEY = "alert_state"
"""The ``meta`` key of the episodes' state."""


class AlertLedger:
    """Alert episodes of one plane, persisted in its store, and their webhook outbox.

    Args:
        store: the matcher's store.
        alerts: the rules.
        context: fields added to every alert's body (the matcher service adds its ``plane``).
        calendar: opening hours gating the places' rules (:class:`AlertEpisodes`).
    """

    def __init__(self, store: Any, alerts: AlertsModel,
                 context: Mapping[str, Any] | None = None, calendar: Any = None) -> None:
        self.store = store
        self.episodes = AlertEpisodes(alerts, calendar)
        self.context = dict(context or {})
        store.write(lambda cursor: cursor.execute(ALERTS_SCHEMA))
        state = store.get_meta(STATE_KEY)
        if state is not None:
            self.episodes.set_state(state)

    def observe(self, observation: Observation,
                meta: Mapping[str, Any] | None = None) -> list[AlertEvent]:
        """Feed one observation; its events, committed with the episodes' state.

        Args:
            observation: the plane now.
            meta: more ``meta`` keys to commit in the same transaction (e.g. how far the
                caller has read the events table), so that they and the episodes' state
                never disagree after a crash.
        """
        events = self.episodes.observe(observation)
        state = self.episodes.get_state()

        def writes(cursor: sqlite3.Cursor) -> None:
            cursor.executemany(
                "INSERT OR IGNORE INTO alerts (episode, state, timestamp, body) "
                "VALUES (?, ?, ?, ?)",
                [(event.episode, event.state, event.timestamp,
                  json.dumps({**event.to_dict(), **self.context})) for event in events],
            )
            cursor.execute(
                "INSERT INTO meta (key, value) VALUES (?, ?) "
                "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (STATE_KEY, json.dumps(state)),
            )
            for key, value in (meta or {}).items():
                cursor.execute(
                    "INSERT INTO meta (key, value) VALUES (?, ?) "
                    "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                    (key, json.dumps(value)),
                )

        if events or state["clock"] is not None:
            self.store.write(writes)
        return events

    def recent(self, limit: int = 100) -> list[dict[str, Any]]:
        """The latest alerts, newest first (for a dashboard), each with its webhooks."""
        rows = self.store.query(
            "SELECT body, delivered FROM alerts ORDER BY id DESC LIMIT ?", (int(limit),))
        return [{**json.loads(body), "delivered_to": json.loads(delivered)}
                for body, delivered in rows]

    def deliver(self, senders: Mapping[str, WebhookSender], limit: int = 100) -> int:
        """Send each webhook, in order, the alerts it has not acknowledged; the number
        delivered. A webhook stops at its first failure (its sender has already retried)."""
        delivered = 0
        for name, sender in senders.items():
            # The webhook's name as it appears in the JSON list of those that acknowledged.
            rows = self.store.query(
                "SELECT id, body FROM alerts WHERE instr(delivered, ?) = 0 ORDER BY id "
                "LIMIT ?", (json.dumps(name), int(limit)))
            for identifier, body in rows:
                if not sender.send(json.loads(body)).delivered:
                    break
                self.store.write(lambda cursor, i=identifier, n=name: _mark(cursor, i, n))
                delivered += 1
        return delivered


def _mark(cursor: sqlite3.Cursor, identifier: int, webhook: str) -> None:
    (done,) = cursor.execute("SELECT delivered FROM alerts WHERE id = ?",
                             (identifier,)).fetchone()
    names = sorted({*json.loads(done), webhook})
    cursor.execute("UPDATE alerts SET delivered = ? WHERE id = ?",
                   (json.dumps(names), identifier))
