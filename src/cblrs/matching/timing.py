"""Capture times: each camera's frame period and the windows of messages fused together.

Cameras do not capture at the same instants: their clocks differ (an NTP error of
milliseconds to tens of milliseconds, or a wrong clock), their frame rates differ, and frames
get dropped. The matcher therefore never groups messages by equal timestamps. It groups them
into **windows** of nearby capture times, and the fusion tracker fuses each message at its
own (clock-corrected) capture time inside its window, the Kalman prediction bridging the
few milliseconds between them.

A window starts at the earliest waiting message, ``start``, and holds every following message
(in capture-time order) captured before ``start + width``, one per camera: a camera's second
message closes the window just before it. The width is ``fraction`` (default 0.3) of the
shortest frame period among the cameras, at most ``max_width_s``: messages of one capture
instant (a few milliseconds apart once clocks are corrected) share a window, while the
capture instants of cameras running at different rates (10 and 15 fps: 33 ms apart at the
closest) stay in windows of their own. While no period is known yet the width is
``max_width_s``.

A window is **complete**, and may be fused, once no further message can join it. Messages
reach the matcher in each camera's own capture order, so for every camera one of these holds:

* it has a message after the window already (it has moved on);
* a *watermark* says every message it captured before the window's end has been delivered;
* its frame period is known and its next frame cannot come before the window's end (a
  camera's next frame comes at least ``1 - slack`` periods after its previous one): this
  releases a window at once when every camera is in it, and does not wait for a slow camera
  whose next frame is due later; until a camera's period is measured, the cameras' frame
  rate, if configured, stands in for it (:class:`PeriodEstimator`);
* it is in the window with the latest capture time of it, or its watermark is at or past
  that time (nothing of it can come between).

The same rules order raw messages in the matcher service (:mod:`cblrs.runtime.matcher.ordering`) and
clock-corrected ones inside the fusion tracker (:class:`WindowBuffer`).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CameraMessage

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

DEFAULT_MAX_WINDOW_S = 0.25
"""Widest window, seconds (also the width while no camera's frame period is known)."""
DEFAULT_WINDOW_FRACTION = 0.3
"""Window width as a fraction of the shortest camera frame period."""
DEFAULT_SLACK = 0.3
"""A camera's next frame comes at least ``1 - slack`` frame periods after its previous one."""
PERIOD_INTERVALS = 8
"""Frame periods are the shortest of this many recent intervals (robust to dropped frames)."""
MINIMUM_INTERVALS = 3
"""Intervals needed before a camera's frame period counts as known."""


class PeriodEstimator:
    """Each camera's frame period from the capture times of its recent messages.

    The period is the shortest of the last :data:`PERIOD_INTERVALS` intervals between a
    camera's consecutive messages, so dropped frames (intervals twice as long, however many)
    do not lengthen it; timestamp jitter shortens it a little, which is the safe side.
    Times must be observed in each camera's capture order; a time not after the camera's
    previous one is ignored.

    Until a camera's period is known, its next frame cannot be predicted and a window it is
    in waits for that frame; ``assumed`` (the cameras' frame period as configured, e.g. from
    their frame rate) predicts it meanwhile (:attr:`predicted`), shortened by any shorter
    interval seen, so a camera faster than assumed is noticed at its second frame.

    Args:
        camera_count: number of cameras C (cameras are indices 0..C-1).
        assumed: the shortest frame period to expect of a camera whose period is not known
            yet, seconds; None: nothing is assumed (such a camera's next frame is awaited).
    """

    def __init__(self, camera_count: int, assumed: float | None = None):
        if assumed is not None and not (assumed > 0 and math.isfinite(assumed)):
            raise ValueError(f"an assumed frame period must be > 0 s, got {assumed}.")
        self.camera_count = int(camera_count)
        self.assumed = None if assumed is None else float(assumed)
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        self._times: list[list[float]] = [[] for _ in range(self.camera_count)]
        self._period = np.full(self.camera_count, np.nan)
        self._shortest = np.full(self.camera_count, np.inf)  # shortest interval seen
        self._last = np.full(self.camera_count, -np.inf)

    def observe(self, camera: int, timestamp: float) -> None:
        """Record one message of ``camera`` captured at ``timestamp`` seconds."""
        times = self._times[camera]
        if times and timestamp <= times[-1]:
            return
        times.append(float(timestamp))
        if len(times) > PERIOD_INTERVALS + 1:
            del times[0]
        self._last[camera] = timestamp
        if len(times) > 1:
            self._shortest[camera] = min(self._shortest[camera], times[-1] - times[-2])
        if len(times) > MINIMUM_INTERVALS:
            # The shortest recent interval: a dropped frame only lengthens intervals, and a
            # period taken too long would predict a camera's next frame too late (a window
            # released before that frame arrived); one taken too short only waits longer.
            # (A handful of numbers: plain Python is faster than numpy here.)
            self._period[camera] = min(map(operator.sub, times[1:], times[:-1]))

    @property
    def periods(self) -> FloatArray:
        """(C,) frame period of each camera, seconds; NaN while unknown."""
        return self._period

    @property
    def predicted(self) -> FloatArray:
        """(C,) the periods that predict each camera's next frame, seconds: the known period,
        else the assumed one (or a shorter interval seen); NaN where neither is known."""
        if self.assumed is None:
            return self._period
        return np.where(np.isnan(self._period), np.fmin(self.assumed, self._shortest),
                        self._period)

    @property
    def last(self) -> FloatArray:
        """(C,) capture time of each camera's latest observed message; -inf before any."""
        return self._last

    def width(self, max_width_s: float, fraction: float) -> float:
        """The window width: ``fraction`` of the shortest known period, at most ``max_width_s``."""
        known = self._period[np.isfinite(self._period)]
        if len(known) == 0:
            return float(max_width_s)
        return float(min(max_width_s, fraction * known.min()))

    def get_state(self) -> list[list[float]]:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return [list(times) for times in self._times]

    def set_state(self, state: Sequence[Sequence[float]]) -> None:
        """Restore a state saved by :meth:`get_state`."""
        self.reset()
        for camera, times in enumerate(state):
            for timestamp in times:
                self.observe(camera, float(timestamp))


def form_window(
    times: FloatArray, cameras: IntArray, width: float
) -> tuple[int, float]:
    """The first window of messages sorted by capture time.

    Args:
        times: (M,) capture times, seconds, non-decreasing (M >= 1).
        cameras: (M,) camera index of each message.
        width: window width, seconds.

    Returns:
        ``(count, end)``: the window holds the first ``count`` messages; ``end`` is where it
        closes (exclusive): ``times[0] + width``, or earlier at a camera's second message.
    """
    start = float(times[0])
    end = start + width
    seen: set[int] = set()
    for index, (timestamp, camera) in enumerate(zip(times.tolist(), cameras.tolist(),
                                                    strict=True)):
        if timestamp >= end:
            return index, end
        if camera in seen:
            return index, float(timestamp)
        seen.add(camera)
    return len(times), end


def waiting_for(
    member_cameras: IntArray,
    member_times: FloatArray,
    end: float,
    passed: BoolArray,
    last: FloatArray,
    periods: FloatArray,
    slack: float = DEFAULT_SLACK,
    delivered: FloatArray | None = None,
) -> BoolArray:
    """The cameras that could still add a message to a window (see the module docstring).

    Args:
        member_cameras: (M,) cameras of the window's messages (distinct).
        member_times: (M,) their capture times, seconds.
        end: where the window closes, seconds (exclusive).
        passed: (C,) whether each camera is known to have nothing more before ``end``
            (a message after the window is known, a watermark, or the camera is offline).
        last: (C,) capture time of each camera's latest known message (members included),
            -inf if none.
        periods: (C,) frame periods, seconds, NaN where unknown.
        slack: a camera's next frame comes at least ``1 - slack`` periods after its last.
        delivered: (C,) a watermark per camera: every message it captured at or before this
            time has been delivered, seconds (NaN or -inf where none is known); None: none.

    Returns:
        (C,) bool; the window is complete when none is set.
    """
    latest = float(member_times.max()) if len(member_times) else -math.inf
    next_due = last + (1.0 - slack) * periods  # NaN where the period is unknown
    with np.errstate(invalid="ignore"):
        settled = passed | (next_due >= end)
        # A camera in the window cannot add a message before its own latest one, nor (with
        # a known period) before its next frame is due, nor at or before its watermark:
        # only a message after the window's latest member could still come, and that would
        # not change the members.
        quiet = (last >= latest) | (next_due >= latest)
        if delivered is not None:
            quiet |= delivered >= latest
    present = np.zeros(len(passed), dtype=bool)
    present[member_cameras] = True
    return ~(settled | (present & quiet))


def window_complete(
    member_cameras: IntArray,
    member_times: FloatArray,
    end: float,
    passed: BoolArray,
    last: FloatArray,
    periods: FloatArray,
    slack: float = DEFAULT_SLACK,
    delivered: FloatArray | None = None,
) -> bool:
    """Whether no further message can join a window (:func:`waiting_for` is all False)."""
    return not waiting_for(member_cameras, member_times, end, passed, last, periods,
                           slack, delivered).any()


@dataclass(frozen=True)
class Window:
    """One window of messages, ready to be fused.

    Attributes:
        messages: the messages, one per camera, in capture-time order.
        cameras: (M,) int64 camera index of each.
        times: (M,) float64 clock-corrected capture times, seconds.
        end: where the window closed, seconds (exclusive).
    """

    messages: list[CameraMessage]
    cameras: IntArray
    times: FloatArray
    end: float


class WindowBuffer:
    """Messages waiting to be fused, released as complete windows of corrected capture time.

    The fusion tracker adds each released group's messages with the watermark the ordering
    guarantees (every message captured at or before it has been delivered) and takes
    windows while they are complete; its clock model supplies each camera's offset, which is
    subtracted from the message timestamps at the moment a window is formed.

    Args:
        camera_count: number of cameras C.
        max_width_s: widest window, seconds.
        fraction: window width as a fraction of the shortest frame period.
        slack: see :func:`window_complete`.
    """

    def __init__(
        self,
        camera_count: int,
        max_width_s: float = DEFAULT_MAX_WINDOW_S,
        fraction: float = DEFAULT_WINDOW_FRACTION,
        slack: float = DEFAULT_SLACK,
    ):
        self.camera_count = int(camera_count)
        self.max_width_s = float(max_width_s)
        self.fraction = float(fraction)
        self.slack = float(slack)
        self.periods = PeriodEstimator(camera_count)
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        self._messages: list[CameraMessage] = []
        self._cameras: list[int] = []
        self._watermark = -math.inf
        # Raw capture time of each camera's latest message already fused (for predictions).
        self._fused_last = np.full(self.camera_count, -np.inf)
        self.periods.reset()

    def __len__(self) -> int:
        return len(self._messages)

    @property
    def watermark(self) -> float:
        """Every raw capture time at or before this has been delivered, seconds."""
        return self._watermark

    def add(self, camera: int, message: CameraMessage) -> None:
        """Queue a message of camera index ``camera``."""
        self._messages.append(message)
        self._cameras.append(int(camera))

    def advance(self, watermark: float) -> None:
        """Record that every message captured at or before ``watermark`` has been delivered."""
        self._watermark = max(self._watermark, float(watermark))

    def next_window(self, offsets: FloatArray, final: bool = False) -> Window | None:
        """Remove and return the earliest window if it is complete (any window if ``final``).

        Args:
            offsets: (C,) each camera's clock offset, seconds (corrected time = raw - offset).
            final: the stream has ended: nothing more will come.

        Returns:
            The window, or None when none is complete (or nothing waits).
        """
        if not self._messages:
            return None
        if len(self._messages) == self.camera_count:
            window = self._simultaneous(offsets)
            if window is not None:
                return window
        raw = np.fromiter((message.timestamp for message in self._messages), np.float64,
                          len(self._messages))
        cameras = np.asarray(self._cameras, np.int64)
        corrected = raw - offsets[cameras]
        order = np.lexsort((cameras, corrected))  # by time, then camera
        width = self.periods.width(self.max_width_s, self.fraction)
        count, end = form_window(corrected[order], cameras[order], width)
        members = order[:count]
        if not final:
            passed = np.zeros(self.camera_count, dtype=bool)
            passed[cameras[order[count:]]] = True
            delivered = self._watermark - offsets  # in corrected time
            with np.errstate(invalid="ignore"):
                passed |= delivered >= end
            last = self._fused_last - offsets
            np.maximum.at(last, cameras[members], corrected[members])
            if not window_complete(cameras[members], corrected[members], end, passed, last,
                                   self.periods.periods, self.slack, delivered):
                return None
        window = Window(
            messages=[self._messages[index] for index in members.tolist()],
            cameras=cameras[members],
            times=corrected[members],
            end=end,
        )
        taken = set(members.tolist())
        self._messages = [m for i, m in enumerate(self._messages) if i not in taken]
        self._cameras = [c for i, c in enumerate(self._cameras) if i not in taken]
        for camera, message in zip(window.cameras.tolist(), window.messages, strict=True):
            self.periods.observe(camera, message.timestamp)
            self._fused_last[camera] = max(self._fused_last[camera], message.timestamp)
        return window

    def _simultaneous(self, offsets: FloatArray) -> Window | None:
        """The common case in short: one message from every camera, all at one corrected
        time. They are one window, complete at once (every camera is in it)."""
        first = self._messages[0].timestamp
        if any(message.timestamp != first for message in self._messages) or len(
                set(self._cameras)) != self.camera_count or offsets.min() != offsets.max():
            return None
        order = np.argsort(self._cameras, kind="stable")
        cameras = np.asarray(self._cameras, np.int64)[order]
        window = Window(
            messages=[self._messages[index] for index in order.tolist()],
            cameras=cameras,
            times=np.full(len(cameras), first - float(offsets[0])),
            end=first - float(offsets[0]) + self.periods.width(self.max_width_s, self.fraction),
        )
        self._messages, self._cameras = [], []
        for camera in cameras.tolist():
            self.periods.observe(camera, first)
            self._fused_last[camera] = max(self._fused_last[camera], first)
        return window

    def get_state(self) -> dict[str, Any]:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "messages": [
                [camera, message.camera_id, message.sequence, message.timestamp, message.frame,
                 message.xyxy.tolist(), message.confidence.tolist(), message.class_id.tolist(),
                 message.colour.tolist()]
                for camera, message in zip(self._cameras, self._messages, strict=True)
            ],
            "watermark": None if math.isinf(self._watermark) else self._watermark,
            "fused_last": [None if math.isinf(value) else value for value in self._fused_last],
            "periods": self.periods.get_state(),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore a state saved by :meth:`get_state`."""
        self.reset()
        for row in state["messages"]:
            camera, camera_id, sequence, timestamp, frame, xyxy, confidence, class_id, colour = row
            self.add(int(camera), CameraMessage(
                str(camera_id), int(sequence), float(timestamp), int(frame),
                np.asarray(xyxy, np.float64).reshape(-1, 4), np.asarray(confidence, np.float64),
                np.asarray(class_id, np.int64), np.asarray(colour, np.int64).reshape(-1, 3),
            ))
        watermark = state["watermark"]
        self._watermark = -math.inf if watermark is None else float(watermark)
        self._fused_last = np.array(
            [-np.inf if value is None else float(value) for value in state["fused_last"]]
        )
        self.periods.set_state(state["periods"])
