"""Ordering: which received messages go to the tracker together, and when.

The matcher service (:mod:`cblrs.runtime.matcher.matcher_service`) and the in-process pipeline
(:func:`cblrs.pipeline.track_scene`) hand messages to the matcher through an
:class:`Orderer`, so both feed it the same windows. Cameras send one message per frame, in
capture order, stamped by their own clocks; the orderer

1. **buffers** them by capture timestamp;
2. **groups** them into windows of nearby timestamps (:mod:`cblrs.matching.timing`): a window
   starts at the earliest waiting message and takes what follows within a fraction of the
   shortest camera frame period, one message per camera. Cameras need not share a clock, a
   frame rate nor capture instants: equal timestamps are not required;
3. **releases** a window, in timestamp order, once no camera can still add a message to it:
   every camera has moved past it, or is in it, or is known (from its recent frame period,
   or the configured frame rate until that is measured) not to capture again before its
   end, or said "offline". A camera that dropped a frame is
   passed once its next message arrives. So that a dead camera does not stall the plane, a
   window is also released when it has waited ``timeout_s`` *and* each camera it still waits
   for has been silent for ``timeout_s``;
4. marks a message **late** when it arrives at or before the timestamp of the last released
   window: it is stored and counted, not tracked.

The released window's timestamp (its latest capture time) is a watermark: every message
captured at or before it by a camera's clock has been delivered. The fusion tracker then
regroups messages by clock-*corrected* capture time (:class:`cblrs.matching.timing.WindowBuffer`)
and fuses each at its own time, so the windows here only decide when messages are complete,
not which are fused together; the tracks are the same however arrivals interleave.

Everything here is pure state: no threads, clocks or I/O (the service passes its clock
reading as ``now``).
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cblrs.matching.timing import (
    DEFAULT_MAX_WINDOW_S,
    DEFAULT_SLACK,
    DEFAULT_WINDOW_FRACTION,
    PeriodEstimator,
    form_window,
    waiting_for,
)


class Timed(Protocol):
    """What the orderer needs of a message (an inbox entry or a camera message)."""

    @property
    def camera_id(self) -> str: ...

    @property
    def timestamp(self) -> float: ...


@dataclass(frozen=True)
class _Waiting:
    timestamp: float
    camera: int
    arrival: float
    entry: Any


class Orderer:
    """Buffer, window and release camera messages in capture order (see the module docstring).

    Args:
        camera_ids: the plane's cameras; released messages are in this order within a time.
        timeout_s: how long a window waits for silent cameras, seconds.
        max_buffered_groups: release the oldest window regardless once more distinct
            timestamps than this wait.
        max_window_s: widest window, seconds.
        window_fraction: window width as a fraction of the shortest frame period.
        slack: a camera's next frame comes at least ``1 - slack`` periods after its last.
        assumed_period_s: the cameras' frame period as configured (their frame rate), to
            predict a camera's next frame until its own period is measured (from its first
            four frames); None: until then a window waits for each camera's next frame.
    """

    def __init__(
        self,
        camera_ids: Sequence[str],
        *,
        timeout_s: float = 2.0,
        max_buffered_groups: int = 10_000,
        max_window_s: float = DEFAULT_MAX_WINDOW_S,
        window_fraction: float = DEFAULT_WINDOW_FRACTION,
        slack: float = DEFAULT_SLACK,
        assumed_period_s: float | None = None,
    ):
        if timeout_s < 0 or not math.isfinite(timeout_s):
            raise ValueError(f"window must be a finite number >= 0, got {timeout_s}.")
        self.camera_ids = list(camera_ids)
        self._index = {name: index for index, name in enumerate(self.camera_ids)}
        self.timeout_s = float(timeout_s)
        self.max_buffered_groups = int(max_buffered_groups)
        self.max_window_s = float(max_window_s)
        self.window_fraction = float(window_fraction)
        self.slack = float(slack)
        count = len(self.camera_ids)
        self._waiting: list[_Waiting] = []  # sorted by (timestamp, camera)
        # Their sort keys, in the same order: bisecting plain tuples compares in C, with no
        # Python key function called per comparison (the receiver thread holds the GIL).
        self._keys: list[tuple[float, int]] = []
        self._times: Counter[float] = Counter()
        self._latest = np.full(count, -np.inf)
        self._periods = PeriodEstimator(count, assumed_period_s)
        self._last_heard = np.full(count, np.nan)
        self._offline = np.zeros(count, dtype=bool)
        self._silence_origin: float | None = None
        self.released: float | None = None
        """Timestamp of the last released window (a message at or before it is late)."""

    # -- input -----------------------------------------------------------------------------

    def restore(self, released: float | None, latest: dict[str, float]) -> None:
        """Resume after a restart: the last released timestamp and each camera's latest."""
        self.released = released
        for camera, timestamp in latest.items():
            if camera in self._index:
                index = self._index[camera]
                self._latest[index] = max(self._latest[index], float(timestamp))

    def is_late(self, timestamp: float) -> bool:
        """Whether a message captured at ``timestamp`` comes after its window was released."""
        return self.released is not None and timestamp <= self.released

    def add(self, entry: Timed, now: float) -> None:
        """Buffer a (not late) message of a known camera, received at ``now``."""
        camera = self._index[entry.camera_id]
        timestamp = float(entry.timestamp)
        key = (timestamp, camera)
        # After those of equal key (as ``insort_right``): arrival order among equals.
        index = bisect.bisect_right(self._keys, key)
        self._keys.insert(index, key)
        self._waiting.insert(index, _Waiting(timestamp, camera, now, entry))
        self._times[timestamp] += 1
        self._latest[camera] = max(self._latest[camera], timestamp)
        self._periods.observe(camera, timestamp)
        self.heard(entry.camera_id, now)

    def heard(self, camera: str, now: float) -> None:
        """Any sign of life of ``camera`` at ``now`` (a message or an "online" status)."""
        index = self._index.get(camera)
        if index is None:
            return
        self._last_heard[index] = now
        if self._silence_origin is None:
            self._silence_origin = now

    def set_offline(self, camera: str, offline: bool) -> None:
        """A camera ended its stream ("offline": not waited for) or started again."""
        index = self._index.get(camera)
        if index is not None:
            self._offline[index] = offline

    # -- output ----------------------------------------------------------------------------

    def release(
        self, now: float, force: bool = False, limit: int | None = None
    ) -> list[tuple[float, list[Any]]]:
        """Remove and return the windows ready at ``now``, oldest first.

        Args:
            now: the caller's clock, seconds (for the silence timeout).
            force: release everything buffered (the stream has ended).
            limit: at most this many windows.

        Returns:
            ``[(timestamp, entries), ...]``: each window's latest capture time and its
            entries, ordered by time and then camera.
        """
        windows: list[tuple[float, list[Any]]] = []
        while self._waiting and (limit is None or len(windows) < limit):
            window = self._next(now, force or len(self._times) > self.max_buffered_groups)
            if window is None:
                break
            windows.append(window)
        return windows

    def _next(self, now: float, force: bool) -> tuple[float, list[Any]] | None:
        head = self._waiting[: 2 * len(self.camera_ids) + 1]
        # The head's (timestamp, camera) sort keys as one array: one conversion, not two.
        keys = np.array(self._keys[: len(head)])
        times, cameras = keys[:, 0], keys[:, 1].astype(np.int64)
        width = self._periods.width(self.max_window_s, self.window_fraction)
        count, end = form_window(times, cameras, width)
        members = head[:count]
        if not force:
            passed = self._offline | (self._latest >= end)
            passed[cameras[count:]] = True
            waiting = waiting_for(cameras[:count], times[:count], end, passed, self._latest,
                                  self._periods.predicted, self.slack)
            if waiting.any() and not self._given_up(members, waiting, now):
                return None
        del self._waiting[:count]
        del self._keys[:count]
        for one in members:
            self._times[one.timestamp] -= 1
            if not self._times[one.timestamp]:
                del self._times[one.timestamp]
        timestamp = max(one.timestamp for one in members)
        self.released = timestamp if self.released is None else max(self.released, timestamp)
        return timestamp, [one.entry for one in members]

    def _given_up(self, members: Iterable[_Waiting], waiting: np.ndarray, now: float) -> bool:
        """The window waited ``timeout_s`` and every camera it waits for is that silent."""
        if now - min(one.arrival for one in members) < self.timeout_s:
            return False
        origin = self._silence_origin if self._silence_origin is not None else now
        heard = np.where(np.isnan(self._last_heard), origin, self._last_heard)
        return bool(np.all(now - heard[waiting] >= self.timeout_s))

    # -- queries ---------------------------------------------------------------------------

    def __len__(self) -> int:
        """Messages waiting."""
        return len(self._waiting)

    def oldest(self) -> float | None:
        """Capture time of the oldest message waiting, or None."""
        return self._waiting[0].timestamp if self._waiting else None

    @property
    def groups(self) -> int:
        """Distinct capture timestamps waiting."""
        return len(self._times)

    @property
    def offline(self) -> list[str]:
        return [name for name, off in zip(self.camera_ids, self._offline.tolist(), strict=True)
                if off]
