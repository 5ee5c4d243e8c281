"""Alerts: rules in the site file, episodes that fire once and clear once, webhooks.

An operator writes rules under ``alerts:`` in the site file (:mod:`~cblrs.alerts.rules`):
zone occupancy above N for T seconds, a visit's dwell above T, a line's crossings above N per
interval, a camera offline, the matcher lagging. :class:`~cblrs.alerts.episodes.AlertEpisodes`
turns the plane's live state, observation after observation, into *episodes*: an episode
fires when its condition has held long enough and clears when it no longer holds — once each,
and its state round-trips through JSON so that a restarted matcher does not fire it again.
:mod:`~cblrs.alerts.webhook` delivers each alert as an HTTP POST signed with HMAC-SHA256 (a
per-webhook secret read from a file or the environment, never from the site file), with
time-outs and retries with back-off. :class:`~cblrs.alerts.ledger.AlertLedger` keeps the
episodes and an outbox of alerts in the matcher's SQLite file.
"""

from cblrs.alerts.episodes import AlertEpisodes, AlertEvent, Observation
from cblrs.alerts.ledger import AlertLedger
from cblrs.alerts.rules import AlertsModel, WebhookModel, load_alerts
from cblrs.alerts.webhook import Delivery, WebhookSender, read_secret, sign

__all__ = [
    "AlertEpisodes",
    "AlertEvent",
    "AlertLedger",
    "AlertsModel",
    "Delivery",
    "Observation",
    "WebhookModel",
    "WebhookSender",
    "load_alerts",
    "read_secret",
    "sign",
]
