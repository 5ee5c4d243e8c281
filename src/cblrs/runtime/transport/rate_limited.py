"""Log lines that repeat per reason at most once every few seconds (rejections, drops)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable


class RateLimitedLog:
    """At most one line per key every ``interval_s``; the next line says how many were held
    back.

    Args:
        logger: where the lines go.
        interval_s: seconds between two lines of the same key.
        clock: monotonic clock.

    Example:
        >>> log = RateLimitedLog(logging.getLogger("cblrs.demo"), interval_s=10)
        >>> log.log(logging.WARNING, "too_old", "rejected %s from %s", "too_old", "CVLab1")
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.logger = logger
        self.interval_s = float(interval_s)
        self._clock = clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def log(self, level: int, key: str, message: str, *args: object) -> bool:
        """Log ``message % args`` unless ``key`` was logged less than ``interval_s`` ago;
        returns whether it was logged."""
        if not self.logger.isEnabledFor(level):
            return False
        now = self._clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.interval_s:
                self._held[key] = self._held.get(key, 0) + 1
                return False
            held = self._held.pop(key, 0)
            self._last[key] = now
        if held:
            message += f" (and {held} more like it in the last {self.interval_s:g} s)"
        self.logger.log(level, message, *args)
        return True
