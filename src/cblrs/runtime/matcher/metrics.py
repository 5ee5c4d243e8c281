"""Prometheus metrics, health and readiness of the matcher service (``cblrs matcher --http``).

:class:`ServiceMetrics` holds the matcher's metrics in a ``prometheus_client`` registry of
its own; the service feeds it as it works (receiver batches, committed tracker batches,
published events) and :class:`MetricsServer` serves, on a small HTTP server of the standard
library:

* ``/metrics`` — the registry in Prometheus' text format (``prometheus_client``'s own
  exposition, never hand-written text);
* ``/healthz`` — 200 while the service runs (its threads and tracker process have not
  failed), else 503 with the reason;
* ``/readyz`` — 200 when it can do its work: started, connected to the broker and (with
  a plane lease) holding it; else 503 with what is missing.

Who may read them: with a token (``cblrs matcher --http-token-file``), ``/metrics`` answers
only a request that carries it (``Authorization: Bearer <token>``, or HTTP basic
authentication with the token as the password: what Prometheus' ``authorization`` and
``basic_auth`` send), and ``/healthz`` and ``/readyz`` answer loopback clients freely and
others with the token. Without a token the server binds to a loopback address only
(:func:`check_exposure`): the metrics name the site's cameras, lines and zones and count
the people crossing them. It then answers only requests whose ``Host`` names a loopback
address (:func:`loopback_host_header`; 421 otherwise), so that a web page opened on the same
machine cannot read them through a name of its own pointed at 127.0.0.1 (DNS rebinding).

Metric names (all labelled ``plane``):

=============================================  ==========================================
``cblrs_messages_received_total``               detection messages received
``cblrs_messages_rejected_total{reason}``       refused by validation, by reason
``cblrs_messages_duplicate_total``              re-deliveries of stored messages
``cblrs_messages_late_total``                   arrived after their time was tracked
``cblrs_messages_retracked_total``              tracked again when late ones were re-tracked
``cblrs_messages_late_tracked_total``           late messages tracked by re-tracking
``cblrs_messages_late_untracked_total``         late ones too old to re-track (no snapshot)
``cblrs_buffered_messages``                     waiting in the ordering buffer
``cblrs_tracker_lag_seconds``                   now minus the capture time last tracked
``cblrs_live_tracks``                           tracks in the last tracker output
``cblrs_stage_duration_seconds{stage}``         receive (validate+store+ack a batch), track
                                                and analytics (per group), commit (per
                                                batch), publish (per group), retrack (per
                                                re-tracking of late messages)
``cblrs_capture_to_track_seconds``              capture to committed track rows, per group
``cblrs_camera_last_seen_timestamp_seconds``    per camera: when its last message arrived
``cblrs_camera_messages_total{camera}``         per camera: messages received
``cblrs_events_total{kind}``                    analytics events committed
``cblrs_events_unpublished``                    events waiting for the broker's ack
``cblrs_line_crossings{line,direction}``        persistent line counts (from the store)
``cblrs_zone_occupancy{zone}``, ``cblrs_zone_visits{zone}``: zones now and in total
=============================================  ==========================================

The capture-to-track buckets sit around the latency target of 20 ms (docs/services.md, the
MQTT benchmark) and reach out to the ordering window's seconds.
"""

from __future__ import annotations

import base64
import hmac
import ipaddress
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import urlsplit

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.exposition import CONTENT_TYPE_LATEST, generate_latest

from cblrs.errors import CblrsError
from cblrs.runtime.addresses import is_loopback_host

logger = logging.getLogger(__name__)

LATENCY_TARGET_S = 0.020
LATENCY_BUCKETS = (
    0.002, 0.005, 0.010, 0.015, 0.020, 0.025, 0.030, 0.040, 0.050, 0.075, 0.100,
    0.250, 0.500, 1.0, 2.0, 3.0, 5.0, 10.0,
)
"""Capture -> track buckets, seconds: dense around the 20 ms target, then the ordering
window's range."""
STAGE_BUCKETS = (
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.010, 0.025, 0.050, 0.100, 0.250,
    0.500, 1.0, 2.5,
)
STAGES = ("receive", "track", "analytics", "commit", "publish", "retrack")

Check = Callable[[], tuple[bool, str]]
"""A health or readiness check: ``(ok, reason)``."""


class ServiceMetrics:
    """The metrics of one matcher service (see the module docstring).

    Args:
        plane_id: the plane (label of every metric).
        camera_ids: the plane's cameras (their per-camera series start at 0).
        registry: the registry to register in (default: a new one of its own).
        wall_clock: seconds since the Unix epoch.
    """

    def __init__(
        self,
        plane_id: int,
        camera_ids: Iterable[str],
        registry: CollectorRegistry | None = None,
        wall_clock: Callable[[], float] = time.time,
    ):
        self.registry = registry or CollectorRegistry()
        self.plane = str(int(plane_id))
        self._wall_clock = wall_clock
        labels = ["plane"]
        registry = self.registry
        self.received = Counter("cblrs_messages_received", "Detection messages received",
                                labels, registry=registry)
        self.rejected = Counter("cblrs_messages_rejected", "Messages refused by validation",
                                [*labels, "reason"], registry=registry)
        self.duplicates = Counter("cblrs_messages_duplicate",
                                  "Re-deliveries of messages already stored", labels,
                                  registry=registry)
        self.late = Counter("cblrs_messages_late",
                            "Messages that arrived after their time was tracked", labels,
                            registry=registry)
        self.retracked_messages = Counter(
            "cblrs_messages_retracked", "Messages tracked again when late ones were re-tracked",
            labels, registry=registry)
        self.late_tracked = Counter("cblrs_messages_late_tracked",
                                    "Late messages tracked by re-tracking", labels,
                                    registry=registry)
        self.late_untracked = Counter(
            "cblrs_messages_late_untracked",
            "Late messages older than every snapshot: never tracked", labels, registry=registry)
        self.buffered = Gauge("cblrs_buffered_messages", "Messages in the ordering buffer",
                              labels, registry=registry)
        self.takeovers = Gauge("cblrs_session_takeovers",
                               "Times another client with the matcher's login took its broker "
                               "session (a shared or stolen login)", labels, registry=registry)
        self.lag = Gauge("cblrs_tracker_lag_seconds",
                         "Wall clock minus the capture time of the last tracked group", labels,
                         registry=registry)
        self.live_tracks = Gauge("cblrs_live_tracks", "Tracks in the last tracker output",
                                 labels, registry=registry)
        self.stage = Histogram("cblrs_stage_duration_seconds", "Duration of a pipeline stage",
                               [*labels, "stage"], buckets=STAGE_BUCKETS, registry=registry)
        self.latency = Histogram("cblrs_capture_to_track_seconds",
                                 "Capture time to committed track rows, per group", labels,
                                 buckets=LATENCY_BUCKETS, registry=registry)
        self.last_seen = Gauge("cblrs_camera_last_seen_timestamp_seconds",
                               "When the camera's last message arrived (Unix time)",
                               [*labels, "camera"], registry=registry)
        self.camera_messages = Counter("cblrs_camera_messages", "Messages received per camera",
                                       [*labels, "camera"], registry=registry)
        self.events = Counter("cblrs_events", "Analytics events committed", [*labels, "kind"],
                              registry=registry)
        self.unpublished = Gauge("cblrs_events_unpublished",
                                 "Analytics events waiting for the broker's acknowledgement",
                                 labels, registry=registry)
        self.line_crossings = Gauge("cblrs_line_crossings", "Crossings counted per line",
                                    [*labels, "line", "direction"], registry=registry)
        self.zone_occupancy = Gauge("cblrs_zone_occupancy", "Confirmed tracks inside a zone",
                                    [*labels, "zone"], registry=registry)
        self.zone_visits = Gauge("cblrs_zone_visits", "Visits of a zone ended so far",
                                 [*labels, "zone"], registry=registry)
        for camera in camera_ids:
            self.camera_messages.labels(self.plane, camera)
        for metric in (self.received, self.duplicates, self.late, self.retracked_messages,
                       self.late_tracked, self.late_untracked):
            metric.labels(self.plane)
        for stage in STAGES:
            self.stage.labels(self.plane, stage)
        self.latency.labels(self.plane)

    # ------------------------------------------------------------------ receiver
    def stored(
        self,
        counters: Mapping[str, int],
        cameras: Mapping[str, int],
        seconds: float,
        received_at: float | None = None,
    ) -> None:
        """A receiver batch was validated, stored and acknowledged.

        Args:
            counters: the batch's counters (``received``, ``rejected.<reason>``,
                ``duplicates``, ``late``).
            cameras: messages per camera in the batch (from the topic).
            seconds: how long the batch took.
            received_at: wall time of the batch (default now).
        """
        plane = self.plane
        when = self._wall_clock() if received_at is None else received_at
        self.received.labels(plane).inc(counters.get("received", 0))
        self.duplicates.labels(plane).inc(counters.get("duplicates", 0))
        self.late.labels(plane).inc(counters.get("late", 0))
        for name, value in counters.items():
            if name.startswith("rejected.") and value:
                self.rejected.labels(plane, name.split(".", 1)[1]).inc(value)
        for camera, count in cameras.items():
            self.camera_messages.labels(plane, camera).inc(count)
            self.last_seen.labels(plane, camera).set(when)
        self.stage.labels(plane, "receive").observe(seconds)

    # ------------------------------------------------------------------ tracker
    def retracked(self, counters: Mapping[str, int]) -> None:
        """Late messages were re-tracked (counters ``retracked``, ``late_tracked``,
        ``late_untracked`` of :func:`cblrs.runtime.matcher.retrack.retrack`)."""
        plane = self.plane
        self.retracked_messages.labels(plane).inc(counters.get("retracked", 0))
        self.late_tracked.labels(plane).inc(counters.get("late_tracked", 0))
        self.late_untracked.labels(plane).inc(counters.get("late_untracked", 0))

    def tracked(
        self,
        groups: Iterable[tuple[float, int]],
        durations: Mapping[str, Iterable[float]],
        events: Mapping[str, int],
        committed_at: float | None = None,
    ) -> None:
        """A tracker batch was committed.

        Args:
            groups: ``(capture timestamp, track rows)`` per group, in time order.
            durations: seconds per stage (``track``, ``analytics``: one per group;
                ``commit``: one per batch).
            events: analytics events committed, by kind.
            committed_at: wall time of the commit (default now).
        """
        plane = self.plane
        now = self._wall_clock() if committed_at is None else committed_at
        last = None
        for timestamp, rows in groups:
            self.latency.labels(plane).observe(max(0.0, now - timestamp))
            last = (timestamp, rows)
        if last is not None:
            self.lag.labels(plane).set(max(0.0, now - last[0]))
            self.live_tracks.labels(plane).set(last[1])
        for stage, values in durations.items():
            for value in values:
                self.stage.labels(plane, stage).observe(value)
        for kind, count in events.items():
            self.events.labels(plane, kind).inc(count)

    def published(self, seconds: float) -> None:
        self.stage.labels(self.plane, "publish").observe(seconds)

    def set_buffered(self, messages: int) -> None:
        self.buffered.labels(self.plane).set(messages)

    def set_takeovers(self, takeovers: int) -> None:
        self.takeovers.labels(self.plane).set(takeovers)

    def set_unpublished(self, events: int) -> None:
        self.unpublished.labels(self.plane).set(events)

    def set_counts(self, summary: Mapping[str, Any], occupancy: Mapping[str, int]) -> None:
        """Persistent counts (:func:`~cblrs.runtime.outputs.analytics_store.count_summary`) and the
        zones' occupancy now."""
        plane = self.plane
        for line, row in summary.get("lines", {}).items():
            for direction in ("positive", "negative"):
                self.line_crossings.labels(plane, line, direction).set(row.get(direction, 0))
        for zone, row in summary.get("zones", {}).items():
            self.zone_visits.labels(plane, zone).set(row.get("visits", 0))
        for zone, count in occupancy.items():
            self.zone_occupancy.labels(plane, zone).set(count)

    def exposition(self) -> bytes:
        """The registry in Prometheus' text format."""
        return generate_latest(self.registry)


MIN_TOKEN_CHARS = 16


class MetricsServerError(CblrsError):
    """The metrics address cannot be used."""


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``:PORT``: the loopback interface) -> ``(host, port)``.

    Raises:
        MetricsServerError: not such an address.
    """
    host, separator, port = text.rpartition(":")
    if not separator or not port.isdigit() or not 0 <= int(port) < 65536:
        raise MetricsServerError(
            f"--http {text!r} is not an address; give HOST:PORT, e.g. 127.0.0.1:9100."
        )
    return (host.strip("[]") or "127.0.0.1"), int(port)


def loopback_host_header(host_header: str) -> bool:
    """Whether an HTTP ``Host`` header names this machine literally: a loopback address,
    ``localhost`` or a name under ``.localhost`` (never resolved: a name an attacker
    controls can resolve to 127.0.0.1)."""
    try:
        host = urlsplit(f"//{host_header}").hostname or ""
    except ValueError:
        return False
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_exposure(host: str, token: str | None) -> None:
    """Refuse to serve the metrics beyond loopback without a token.

    Raises:
        MetricsServerError: ``host`` is not a loopback address and there is no token.
    """
    if token is None and not is_loopback_host(host):
        raise MetricsServerError(
            f"--http {host} serves the metrics beyond this machine, so it needs "
            "--http-token-file FILE (scrapers send the token as a bearer token or basic-auth "
            "password); without it, serve on 127.0.0.1."
        )


def request_allowed(path: str, client: str, authorization: str, token: str | None) -> bool:
    """Whether a request for ``path`` from address ``client`` with this ``Authorization``
    header is answered: always without a token; with one, health checks from loopback
    clients, and anything that carries the token."""
    if token is None:
        return True
    if path != "/metrics" and is_loopback_host(client):
        return True
    return _authorized(authorization, token)


def _authorized(header: str, token: str) -> bool:
    """Whether an Authorization header carries ``token`` (bearer, or basic-auth password)."""
    scheme, _, value = header.strip().partition(" ")
    value = value.strip()
    if scheme.lower() == "basic":
        try:
            value = base64.b64decode(value, validate=True).decode().partition(":")[2]
        except (ValueError, UnicodeDecodeError):
            return False
    elif scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(value.encode(), token.encode())


class _BoundedServer(ThreadingHTTPServer):
    """A thread per connection, at most ``max_connections`` at once (the rest closed)."""

    def __init__(self, address: tuple[str, int], handler: Any, max_connections: int):
        self.max_connections = max(1, int(max_connections))
        self._slots = threading.BoundedSemaphore(self.max_connections)
        super().__init__(address, handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            logger.warning("metrics: %d connections open; closed one from %s",
                           self.max_connections, client_address[0])
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class MetricsServer:
    """``/metrics``, ``/healthz`` and ``/readyz`` over HTTP, in a thread of its own.

    Args:
        address: ``(host, port)``; port 0 picks a free one (see :attr:`port`).
        exposition: returns the ``/metrics`` body.
        health: the ``/healthz`` check.
        ready: the ``/readyz`` check.
        token: the token a request must carry (see the module docstring); None: no
            token, and then ``address`` must be a loopback one.
        idle_timeout_s: a connection that sends nothing for this long is closed.
        max_connections: connections served at once; past them a new one is closed at
            once (idle connections must not exhaust the matcher's threads).

    Raises:
        MetricsServerError: the address cannot be bound, or is beyond loopback without a
            token (one sentence).
    """

    def __init__(
        self,
        address: tuple[str, int],
        exposition: Callable[[], bytes],
        health: Check,
        ready: Check,
        token: str | None = None,
        idle_timeout_s: float = 10.0,
        max_connections: int = 32,
    ):
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise MetricsServerError(
                f"the metrics token has {len(token)} characters; give at least "
                f"{MIN_TOKEN_CHARS} (e.g. python -c 'import secrets; "
                "print(secrets.token_urlsafe(32))')."
            )
        check_exposure(address[0], token)
        routes: dict[str, Callable[[], tuple[int, str, bytes]]] = {
            "/metrics": lambda: (200, CONTENT_TYPE_LATEST, exposition()),
            "/healthz": lambda: _check_answer(health),
            "/readyz": lambda: _check_answer(ready),
        }

        class Handler(BaseHTTPRequestHandler):
            timeout = idle_timeout_s  # on the socket: a silent client is let go

            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                route = routes.get(path)
                headers = {}
                if token is None and not loopback_host_header(self.headers.get("Host", "")):
                    # Token-less means loopback-only: a page that points a name of its own at
                    # 127.0.0.1 (DNS rebinding) must not read the site's names and counts.
                    status, kind = 421, "text/plain; charset=utf-8"
                    body = b"this server answers loopback host names only (127.0.0.1)\n"
                    logger.warning("metrics: refused %s for host %r (not a loopback name)",
                                   path, self.headers.get("Host", "")[:100])
                elif route is None:
                    status, kind, body = 404, "text/plain; charset=utf-8", b"not found\n"
                elif not request_allowed(path, self.client_address[0],
                                         self.headers.get("Authorization", ""), token):
                    status, kind = 401, "text/plain; charset=utf-8"
                    body = b"the metrics need the token (bearer or basic-auth password)\n"
                    headers["WWW-Authenticate"] = 'Basic realm="cblrs metrics"'
                    logger.warning("metrics: refused %s from %s (no valid token)", path,
                                   self.client_address[0])
                else:
                    try:
                        status, kind, body = route()
                    except Exception as error:  # a scrape must never stop the matcher
                        logger.exception("metrics endpoint %s failed", self.path)
                        status, kind = 500, "text/plain; charset=utf-8"
                        body = ("error: " + str(error) + "\n").encode()
                self.send_response(status)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("X-Content-Type-Options", "nosniff")
                self.send_header("Cache-Control", "no-store")
                for name, value in headers.items():
                    self.send_header(name, value)
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:
                logger.debug("metrics %s - %s", self.address_string(), format % args)

        try:
            self._server = _BoundedServer(address, Handler, max_connections)
        except OSError as error:
            raise MetricsServerError(
                f"cannot serve metrics on {address[0]}:{address[1]}: "
                f"{error.strerror or error}."
            ) from None
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        name="cblrs-metrics", daemon=True)

    @property
    def port(self) -> int:
        """The port it listens on (the one chosen when 0 was asked)."""
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        """The base URL of /metrics, /healthz and /readyz."""
        host = self._server.server_address[0]
        return f"http://{host if isinstance(host, str) else host.decode()}:{self.port}"

    def start(self) -> MetricsServer:
        """Start serving in a background thread."""
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving."""
        if self._thread.is_alive():  # shutdown() waits for serve_forever, so only if it runs
            self._server.shutdown()
            self._thread.join(5)
        self._server.server_close()


def _check_answer(check: Check) -> tuple[int, str, bytes]:
    ok, reason = check()
    body = (("ok" if ok else "not ok") + (f": {reason}" if reason else "") + "\n").encode()
    return (200 if ok else 503), "text/plain; charset=utf-8", body
