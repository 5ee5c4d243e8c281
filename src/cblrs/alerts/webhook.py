"""Alerts as signed HTTP POSTs, with time-outs and retries with back-off.

Each request carries the alert as JSON and three headers:

* ``X-Cblrs-Timestamp``: seconds since 1970 when it was signed;
* ``X-Cblrs-Signature``: ``sha256=`` and the hex HMAC-SHA256, keyed with the webhook's
  secret, of ``"<timestamp>." + body`` (a receiver recomputes it, compares in constant time
  and refuses old timestamps: a replayed request is stale, a forged one does not match);
* ``X-Cblrs-Episode``: the episode id and state (``crowd/market/3 fired``), for
  de-duplication: a request whose answer was lost is sent again.

An attempt fails on a connection error, a time-out, a 5xx or a 429 answer, and is retried
after ``backoff_s * 2**n`` seconds (capped at ``max_backoff_s``) up to ``retries`` times; any
other 4xx answer is final (the receiver refused the request: retrying would not change it),
and so is a redirect, which is never followed (a receiver could otherwise send the matcher's
requests to an address of the matcher's own network).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import stat
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cblrs.alerts.rules import AlertsError, WebhookModel

logger = logging.getLogger(__name__)

SIGNATURE_HEADER = "X-Cblrs-Signature"
TIMESTAMP_HEADER = "X-Cblrs-Timestamp"
EPISODE_HEADER = "X-Cblrs-Episode"


class _NoRedirects(urllib.request.HTTPRedirectHandler):
    """Never follow a redirect: a receiver could point the matcher at an address of its own
    network (a metadata service, a port on loopback), with the alert's headers."""

    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None


_OPENER = urllib.request.build_opener(_NoRedirects)


def sign(secret: bytes, timestamp: str, body: bytes) -> str:
    """The signature header's value: ``sha256=<hex HMAC-SHA256 of "timestamp." + body>``."""
    digest = hmac.new(secret, timestamp.encode() + b"." + body, hashlib.sha256).hexdigest()
    return f"sha256={digest}"


def verify(secret: bytes, timestamp: str, body: bytes, signature: str,
           now: float | None = None, tolerance_s: float = 300.0) -> bool:
    """What a receiver checks: the signature matches and the timestamp is recent."""
    try:
        age = abs((time.time() if now is None else now) - float(timestamp))
    except ValueError:
        return False
    return age <= tolerance_s and hmac.compare_digest(sign(secret, timestamp, body), signature)


def read_secret(webhook: WebhookModel, folder: Path | None = None,
                environment: dict[str, str] | None = None) -> bytes:
    """The webhook's HMAC secret, from its file (owner-only) or environment variable.

    Args:
        webhook: the webhook.
        folder: relative ``secret_file`` names are relative to it (the site file's folder).
        environment: the environment (default ``os.environ``).

    Raises:
        AlertsError: the file or variable is missing or empty, or the file is readable by
            others than its owner.
    """
    if webhook.secret_env is not None:
        value = (os.environ if environment is None else environment).get(webhook.secret_env)
        if not value:
            raise AlertsError(
                f"webhook {webhook.name}: the environment variable {webhook.secret_env} "
                "(its secret) is not set."
            )
        return value.encode()
    assert webhook.secret_file is not None
    path = Path(webhook.secret_file)
    if folder is not None and not path.is_absolute():
        path = folder / path
    try:
        mode = path.stat().st_mode
        secret = path.read_bytes().strip()
    except OSError as error:
        raise AlertsError(
            f"webhook {webhook.name}: cannot read its secret file {path}: "
            f"{error.strerror or error}."
        ) from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise AlertsError(
            f"webhook {webhook.name}: its secret file {path} is readable by others "
            f"(mode {stat.S_IMODE(mode):04o}); chmod 600 it."
        )
    if not secret:
        raise AlertsError(f"webhook {webhook.name}: its secret file {path} is empty.")
    return secret


@dataclass(frozen=True)
class Delivery:
    """How one alert's delivery went.

    Attributes:
        delivered: a 2xx answer came.
        attempts: requests sent.
        status: the last HTTP status (None: no answer).
        error: the last failure as a sentence (None when delivered).
    """

    delivered: bool
    attempts: int
    status: int | None
    error: str | None = None


class WebhookSender:
    """POSTs alerts to one webhook, signed, with time-outs and retries with back-off.

    :meth:`send` delivers one body and returns how it went (the caller's thread waits);
    :meth:`submit` queues it for a background thread, in order, so the matcher never waits
    for a slow receiver.
    """

    def __init__(self, webhook: WebhookModel, secret: bytes,
                 sleep: Callable[[float], bool] | None = None) -> None:
        self.webhook = webhook
        self._secret = secret
        self._stop = threading.Event()
        self._sleep = sleep or self._stop.wait
        self._queue: list[dict[str, Any]] = []
        self._wake = threading.Condition()
        self._thread: threading.Thread | None = None
        self.results: list[Delivery] = []

    def send(self, body: dict[str, Any]) -> Delivery:
        """Deliver ``body`` (JSON) now, retrying as configured."""
        payload = json.dumps(body, separators=(",", ":"), sort_keys=True).encode()
        episode = f"{body.get('episode', '')} {body.get('state', '')}".strip()
        status: int | None = None
        error = "not sent"
        attempts = 0
        for attempt in range(self.webhook.retries + 1):
            if attempt:
                delay = min(self.webhook.backoff_s * 2 ** (attempt - 1),
                            self.webhook.max_backoff_s)
                if self._sleep(delay):
                    break  # stopped
            attempts += 1
            status, error, final = self._attempt(payload, episode)
            if status is not None and 200 <= status < 300:
                return Delivery(True, attempts, status)
            if final:
                break
        logger.warning("webhook %s: %s not delivered after %d attempt%s: %s", self.webhook.name,
                       episode or "alert", attempts, "" if attempts == 1 else "s", error)
        return Delivery(False, attempts, status, error)

    def _attempt(self, payload: bytes, episode: str) -> tuple[int | None, str, bool]:
        """One request: (status, failure sentence, whether the failure is final)."""
        timestamp = f"{time.time():.3f}"
        request = urllib.request.Request(
            self.webhook.url, data=payload, method="POST",
            headers={"Content-Type": "application/json", "User-Agent": "cblrs-alerts",
                     TIMESTAMP_HEADER: timestamp, EPISODE_HEADER: episode,
                     SIGNATURE_HEADER: sign(self._secret, timestamp, payload)},
        )
        try:
            with _OPENER.open(request, timeout=self.webhook.timeout_s) as answer:
                return int(answer.status), "", False
        except urllib.error.HTTPError as error:
            if 300 <= error.code < 400:
                where = str(error.headers.get("Location", ""))[:200]
                return error.code, (f"HTTP {error.code}: a redirect (to {where!r}) is not "
                                    "followed; give the webhook's final address"), True
            retry = error.code >= 500 or error.code == 429
            return error.code, f"HTTP {error.code} {error.reason}", not retry
        except (urllib.error.URLError, OSError) as error:
            reason = getattr(error, "reason", error)
            return None, f"{reason}", False

    # ------------------------------------------------------------------ background
    def submit(self, body: dict[str, Any]) -> None:
        """Queue ``body`` for the background thread (started on first use)."""
        with self._wake:
            self._queue.append(body)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name=f"cblrs-webhook-{self.webhook.name}")
                self._thread.start()
            self._wake.notify()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._wake:
                while not self._queue and not self._stop.is_set():
                    self._wake.wait()
                if self._stop.is_set():
                    return
                body = self._queue.pop(0)
            self.results.append(self.send(body))

    def pending(self) -> int:
        """Bodies queued and not yet attempted."""
        with self._wake:
            return len(self._queue)

    def close(self, timeout: float = 5.0) -> None:
        """Stop the background thread (what is queued stays undelivered)."""
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
