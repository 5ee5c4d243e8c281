"""How a long-running command (``cblrs camera``, ``matcher``) stops on SIGINT or SIGTERM,
whatever it is doing then.

* The first signal asks it to stop cleanly (a camera waits a few seconds for the broker, a
  matcher commits what it tracked) once it has something to stop (:meth:`StopSignals.arm`);
  before that — loading a data set or a model, connecting to a broker that does not answer
  — it raises :class:`Interrupted`, which ends the start-up at once.
* A second signal raises :class:`Interrupted` wherever the command is (a stop that waits
  on something is cut short).
* A watchdog thread ends the process when that does not happen in time: a clean stop that
  takes longer than ``deadline_s``, or an interruption not done within
  :data:`INTERRUPT_GRACE_S`. Python runs signal handlers in the main thread only, between
  two bytecodes: a main thread blocked in a library call (a stream that stopped sending, an
  inference, a C-level wait) would otherwise ignore every signal. The watchdog learns of
  signals through :func:`signal.set_wakeup_fd`, which the interpreter writes at once.

Every way says what happened in one line on stderr and exits with the command's code; what
a camera has not sent stays in its spool, what a matcher has not committed stays pending in
its database (both SQLite: an abrupt end loses nothing committed).
"""

from __future__ import annotations

import logging
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable

logger = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)
INTERRUPT_GRACE_S = 3.0
"""How long an interruption (a signal during the start-up, or a second one) may take to end
the process before the watchdog ends it."""


class Interrupted(BaseException):
    """A signal ended the command before or during its stop (a BaseException, like
    KeyboardInterrupt: ``except Exception`` clauses let it through)."""

    def __init__(self, signum: int):
        self.signum = signum
        self.name = signal.Signals(signum).name
        super().__init__(self.name)

    @property
    def exit_code(self) -> int:
        """The shell's convention: 128 + the signal's number (130 for SIGINT)."""
        return 128 + self.signum


class StopSignals:
    """SIGINT/SIGTERM handling of one command (see the module docstring).

    Args:
        command: its name in messages (``cblrs camera``).
        deadline_s: how long a clean stop may take before the watchdog ends the process.
        exit_code: the watchdog's exit code (called then, from its thread).
    """

    def __init__(
        self, command: str, deadline_s: float = 15.0, exit_code: Callable[[], int] = lambda: 1
    ):
        self.command = command
        self.deadline_s = float(deadline_s)
        self.exit_code = exit_code
        self.received: str | None = None
        self._stop: Callable[[], None] | None = None
        self._finished = threading.Event()
        self._previous: dict[int, object] = {}
        self._wakeup: tuple[int, int] | None = None
        self._previous_fd = -1
        self._first = signal.SIGTERM  # the first signal the watchdog saw

    def install(self) -> StopSignals:
        """Handle SIGINT and SIGTERM from now on (main thread only) and start the watchdog."""
        for signum in SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)
        read, write = os.pipe()
        os.set_blocking(write, False)
        self._wakeup = (read, write)
        self._previous_fd = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        threading.Thread(
            target=self._watch, args=(read,), name="cblrs-stop-watchdog", daemon=True
        ).start()
        return self

    def arm(self, stop: Callable[[], None]) -> None:
        """From now on the first signal calls ``stop()`` (a clean stop) instead of raising."""
        self._stop = stop

    @property
    def armed(self) -> bool:
        """Whether a first signal now stops the command cleanly."""
        return self._stop is not None

    def finished(self) -> None:
        """The stop is over (the command only reports now): the watchdog stands down."""
        self._finished.set()
        if self._wakeup is not None:
            try:
                os.write(self._wakeup[1], b"\0")  # not a signal: wakes the watchdog up
            except OSError:
                pass

    def restore(self) -> None:
        """Stand the watchdog down and put back what :meth:`install` replaced (tests run
        commands in-process)."""
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)  # type: ignore[arg-type]
        self._previous.clear()
        if self._wakeup is not None:
            signal.set_wakeup_fd(self._previous_fd)  # before its pipe closes
        self.finished()
        if self._wakeup is not None:
            os.close(self._wakeup[1])  # the watchdog closes the other end
            self._wakeup = None

    def _handle(self, signum: int, frame: object) -> None:
        name = signal.Signals(signum).name
        if self._stop is None or self.received is not None:
            self.received = self.received or name
            raise Interrupted(signum)
        self.received = name
        logger.info("%s: stopping (a second signal stops at once)", name)
        self._stop()

    def _watch(self, read: int) -> None:
        """The watchdog: wait for signals (bytes on the wakeup pipe) and end the process
        when what they ask is not done in time."""
        count = 0
        deadline: float | None = None
        handled: float | None = None  # by then the main thread has begun the clean stop
        try:
            while not self._finished.is_set():
                due = min(deadline or float("inf"), handled or float("inf"))
                timeout = None if due == float("inf") else max(0.0, due - time.monotonic())
                ready, _, _ = select.select([read], [], [], timeout)
                if self._finished.is_set():
                    return
                if ready:
                    data = os.read(read, 64)
                    if not data:
                        return  # restored: the pipe is closed
                    signals = sum(1 for byte in data if byte in SIGNALS)
                    if not signals:
                        continue
                    first = count == 0
                    if first:
                        self._first = next(byte for byte in data if byte in SIGNALS)
                    count += signals
                    now = time.monotonic()
                    if first and self._stop is not None and count == 1:
                        deadline = now + self.deadline_s  # a clean stop
                        handled = now + INTERRUPT_GRACE_S
                    else:  # an interruption: the main thread raises, or is blocked
                        deadline = min(deadline or float("inf"), now + INTERRUPT_GRACE_S)
                    continue
                now = time.monotonic()
                if handled is not None and now >= handled:
                    handled = None
                    if self.received is None:  # the main thread is blocked: no clean stop
                        self._end(count, blocked=True)
                if deadline is not None and now >= deadline:
                    self._end(count)
        finally:
            os.close(read)

    def _end(self, count: int, blocked: bool = False) -> None:
        try:
            code = int(self.exit_code())
        except Exception:  # the state it reads may be half closed: still exit
            code = 1
        if blocked or count > 1 or self._stop is None:
            what = (
                f"did not begin to stop within {INTERRUPT_GRACE_S:g} s of "
                f"{signal.Signals(self._first).name} (blocked in a call that ignores "
                "signals)"
            )
        else:
            what = f"did not stop within {self.deadline_s:g} s of {self.received}"
        sys.stderr.write(f"{self.command}: {what}: ended at once (exit {code}).\n")
        sys.stderr.flush()
        os._exit(code)


def install_stop_handlers(stop: Callable[[], None]) -> None:
    """Call ``stop()`` on SIGINT / SIGTERM (main thread only), every time (no second-signal
    or watchdog: :class:`StopSignals` adds those)."""

    def handle(signum: int, frame: object) -> None:
        logger.info("%s: stopping", signal.Signals(signum).name)
        stop()

    for signum in SIGNALS:
        signal.signal(signum, handle)
