"""The state of a :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`: what its
constructor sets up (ordering, confirmations, reporter, alerts, the events and locks its
threads share), and how a failure stops it.

Its threads are mixins of this class, one module each: the receiver
(:mod:`~cblrs.runtime.matcher.matcher_receiver`: validate, store, acknowledge, buffer) and the
releaser and collector (:mod:`~cblrs.runtime.matcher.matcher_releaser`: release groups to the
tracker process, publish its tracks); the lifecycle and the queries are
:class:`~cblrs.runtime.matcher.matcher_service.MatcherService` itself.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from cblrs.errors import CblrsError
from cblrs.runtime.matcher.confirmations import ConfirmationBuffer
from cblrs.runtime.matcher.lease import PlaneLease
from cblrs.runtime.matcher.metrics import ServiceMetrics
from cblrs.runtime.matcher.ordering import Orderer
from cblrs.runtime.matcher.retention import RetentionPolicy
from cblrs.runtime.matcher.retrack import RetrackPolicy
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.tracker_process import Batch, TrackerProcess, TrackerProcessError
from cblrs.runtime.outputs.analytics_service import ServiceReporter
from cblrs.runtime.transport.rate_limited import RateLimitedLog
from cblrs.runtime.transport.topics import validate_camera_id
from cblrs.runtime.wire import ValidationPolicy

logger = logging.getLogger("cblrs.runtime.matcher.matcher_service")
"""The service's logger: its parts log under the one name."""


class LeaseLost(RuntimeError):
    """Another matcher instance took the plane: this one stopped acknowledging."""


class ServiceClock:
    """Monotonic seconds that stand still while ``connected()`` is False.

    Args:
        connected: whether the service is currently connected to its broker.
        monotonic: the underlying clock.
    """

    def __init__(
        self, connected: Callable[[], bool], monotonic: Callable[[], float] = time.monotonic
    ):
        self._connected = connected
        self._monotonic = monotonic
        self._paused = 0.0
        self._down_since: float | None = None
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            now = self._monotonic()
            if not self._connected():
                if self._down_since is None:
                    self._down_since = now
                return now - self._paused - (now - self._down_since)
            if self._down_since is not None:
                self._paused += now - self._down_since
                self._down_since = None
            return now - self._paused


__all__ = ["LeaseLost", "ServiceClock", "_MatcherState"]  # _MatcherState: in the API reference
# (the attributes of MatcherService are set there)


class _MatcherState:
    """What a matcher service holds (its constructor: see
    :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`)."""

    lag: Callable[[float], float]  # MatcherService.lag, handed to the alert service

    def __init__(
        self,
        transport: Any,
        store: RuntimeStore,
        matcher: Any,
        plane_id: int,
        camera_ids: Sequence[str],
        *,
        policy: ValidationPolicy | None = None,
        window_s: float = 2.0,
        publish_tracks: bool = True,
        max_buffered_groups: int = 10_000,
        batch_size: int = 500,
        groups_per_commit: int = 50,
        settings: dict[str, Any] | None = None,
        observer: Any = None,
        wall_clock: Callable[[], float] = time.time,
        lease: bool | None = None,
        allow_other_database: bool = False,
        confirm_interval_s: float = 0.25,
        log_interval_s: float = 10.0,
        retention: RetentionPolicy | None = RetentionPolicy(),  # noqa: B008 (frozen)
        analytics: Any = None,
        metrics: ServiceMetrics | None = None,
        live_interval_s: float | None = 1.0,
        retrack: RetrackPolicy | None = RetrackPolicy(),  # noqa: B008 (frozen)
        alerts: Any = None,
        alert_senders: dict[str, Any] | None = None,
        camera_fps: float | None = None,
    ):
        if window_s < 0 or not math.isfinite(window_s):
            raise ValueError(f"window must be a finite number >= 0, got {window_s}.")
        self.camera_ids = [validate_camera_id(name) for name in camera_ids]
        if not self.camera_ids or len(set(self.camera_ids)) != len(self.camera_ids):
            raise ValueError(f"camera ids must be distinct and non-empty, got {camera_ids}.")
        self.transport = transport
        self.store = store
        self.matcher = matcher
        self.plane_id = int(plane_id)
        base = policy or ValidationPolicy()
        self.policy = ValidationPolicy(
            known_cameras=frozenset(self.camera_ids),
            bits=base.bits,
            max_age_s=base.max_age_s,
            max_future_s=base.max_future_s,
            max_bytes=base.max_bytes,
        )
        self.window_s = float(window_s)
        self.publish_tracks = publish_tracks
        self.max_buffered_groups = int(max_buffered_groups)
        if camera_fps is not None and not (camera_fps > 0 and math.isfinite(camera_fps)):
            raise ValueError(f"camera fps must be a finite number > 0, got {camera_fps}.")
        self.camera_fps = camera_fps
        self._orderer = Orderer(
            self.camera_ids, timeout_s=self.window_s, max_buffered_groups=self.max_buffered_groups,
            assumed_period_s=None if camera_fps is None else 1.0 / camera_fps)
        self.batch_size = int(batch_size)
        self.groups_per_commit = max(1, int(groups_per_commit))
        self.observer = observer
        self._wall_clock = wall_clock
        # The silence timeout counts only while messages can arrive: connected, and (NATS)
        # the plane's consumer has delivered what its stream holds.
        self.clock = ServiceClock(lambda: bool(getattr(
            transport, "caught_up", getattr(transport, "connected", True))))
        self._settings = {"plane_id": self.plane_id, "camera_ids": self.camera_ids}
        self._settings.update(settings or {})

        self._inbox: deque[tuple[str, Any, float]] = deque()
        self._arrived = threading.Event()
        self._offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._final_offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._offline_at: dict[str, float | None] = dict.fromkeys(self.camera_ids, None)
        self._started_at = wall_clock()
        self._active_this_run: set[str] = set()
        self._last_delivery = 0.0
        self._stop = threading.Event()
        self._flush_requested = threading.Event()
        self._wake = threading.Event()
        self._received_all = threading.Event()
        self._state_lock = threading.RLock()
        self._inflight: deque[Batch] = deque()  # sent to the tracker process, not answered
        self._tracker: TrackerProcess | None = None
        self._threads: list[threading.Thread] = []
        self._failure: BaseException | None = None
        self._started = False
        self.matcher_id = str(getattr(transport, "client_id", f"matcher{self.plane_id}"))
        self._use_lease = (getattr(transport, "lease", None) is None) if lease is None else lease
        self._allow_other_database = allow_other_database
        self._lease: PlaneLease | None = None
        self._receiving = threading.Event()
        self._connections = 0
        self._session_present = False
        self._confirmations = ConfirmationBuffer(self.plane_id, self.matcher_id)
        self.confirm_interval_s = float(confirm_interval_s)
        self._last_confirmation = 0.0
        self._rejections = RateLimitedLog(logger, log_interval_s)
        self._retained_warned: set[str] = set()
        self.retention = retention
        self.retrack = retrack
        self._late_at: float | None = None  # service clock of the last late message waiting
        self._retracks_inflight = 0
        self.analytics = analytics
        self.reporter = ServiceReporter(
            transport, store, self.plane_id, self.camera_ids,
            places=None if analytics is None else analytics.places, metrics=metrics,
            live_interval_s=live_interval_s,
        )
        self.alerts: Any = None  # an AlertService when the site has alert rules
        if alerts is not None and alerts.rules:
            # lazy: the alerts' rule models (pydantic) cost a matcher without rules about
            # 0.25 CPU-s to import, paid at every start
            from cblrs.runtime.outputs.alert_service import AlertService

            # The opening hours that gate counting gate the places' alerts too.
            calendar = None if analytics is None else analytics.engine.config.calendar
            self.alerts = AlertService(transport, store, self.plane_id, self.camera_ids,
                                       alerts, alert_senders or {}, self.reporter, self.lag,
                                       calendar=calendar)

    def _fail(self, error: BaseException, role: str) -> None:
        """Record the first failure and stop the service (``stop`` raises it)."""
        # A cause the operator can fix (a deleted database, a lost lease) is one sentence;
        # anything else is a bug and keeps its traceback.
        expected = isinstance(error, CblrsError | LeaseLost) or (
            isinstance(error, TrackerProcessError) and "Traceback" not in str(error))
        logger.error("matcher service %s failed: %s", role, error,
                     exc_info=None if expected else error)
        if self._failure is None:
            self._failure = error
        self._stop.set()
        self._arrived.set()
        self._wake.set()
