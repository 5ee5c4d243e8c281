"""Logging in without taking logins from others: the back-off of failed logins and the
queue of logins being checked.

* :class:`LoginLimiter`: after a few failures for a user name or from one client address,
  each further failure locks that name (address) for twice as long as the previous one, up to
  five minutes (429 with ``Retry-After``). A browser that has logged in as a user before
  carries a **device cookie** for that name (:func:`device_cookie`): its logins of that name
  meet only their own device's lock, never the name's or the address's. Every local client
  is 127.0.0.1 (and every client behind a proxy the proxy's address), so an address's lock
  alone let anyone who reached the port keep the admin out by failing logins under any name;
  they cannot fail with the admin's device, whose cookie they do not have.
* :class:`LoginSlots`: a login's password is checked with scrypt (128 MiB, a good part of a
  second), two at a time; one user name from one address (and one known device: the app
  keys a device's logins apart) has at most one login waiting or being checked, the next
  gets 429 at once. Before, a viewer sending its own right password
  on 16 connections at once kept the queue full: another user's login waited 20 s (the
  back-off counts failures only). A locked name is refused before it queues.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import secrets
import threading
import time
from collections.abc import AsyncIterator, Callable

LOGINS_AT_ONCE = 2
"""Passwords checked at once (scrypt takes 128 MiB and a good part of a second each)."""
DEVICE_DAYS = 90
"""How long a browser's device cookie lasts after its last login."""


def device_cookie(name: str, secret: str, nonce: str | None = None) -> str:
    """A device cookie's value for user ``name``: a random ``nonce`` and its HMAC under the
    user's ``secret`` (their password hash, which only the server holds: a new password ends
    every device of the user; a user without one has no devices)."""
    nonce = nonce if nonce is not None else secrets.token_urlsafe(12)
    mac = hmac.new(secret.encode(), f"cblrs device\n{name}\n{nonce}".encode(), hashlib.sha256)
    return f"{nonce}.{mac.hexdigest()[:32]}"


def device_of(cookie: str, name: str, secret: str) -> str | None:
    """The device (its nonce) that ``cookie`` names if it is a valid device cookie of user
    ``name`` (under their ``secret``), else None."""
    nonce, _, _ = cookie.partition(".")
    if not secret or not nonce or len(cookie) > 128:
        return None
    valid = hmac.compare_digest(device_cookie(name, secret, nonce).encode(), cookie.encode())
    return nonce if valid else None


class LoginRefused(Exception):
    """A login is refused: ``status`` (401, 429, 503), one sentence, the seconds to wait."""

    def __init__(self, status: int, message: str, retry_after_s: float = 0.0):
        super().__init__(message)
        self.status = status
        self.retry_after_s = retry_after_s


class LoginLimiter:
    """Exponential back-off of failed logins, per user name, per client address and per
    known device.

    After ``free_per_user`` failures for a name (``free_per_client`` from an address) each
    further failure locks that name (address) for ``base_s`` doubled per failure, at most
    ``max_s``. A name's lock holds only for the addresses that failed for that name: anyone
    who knows an admin's name could otherwise keep the admin out for good (a failure every
    ``max_s``), as the right password is refused during a lock; a guesser on many addresses
    gets one try per address before the name's lock slows it there too. A success clears
    its own address's failures for the name, not the name's count (which would give a guesser
    fresh tries whenever the owner logs in); the count is forgotten after ``2 * max_s``
    without a failure.

    A login from a known ``device`` of the name (a valid device cookie, see
    :func:`device_of`) meets that device's lock only (``free_per_user`` failures, then the
    same doubling), and its failures count for that device only: on a shared address (every
    local client is 127.0.0.1; behind a proxy, the proxy's) the name's and the address's
    locks are the guesser's as much as the owner's, and the device is what tells them apart.
    """

    def __init__(self, free_per_user: int = 5, free_per_client: int = 20, base_s: float = 1.0,
                 max_s: float = 300.0, clock: Callable[[], float] = time.monotonic):
        self.free = {"user": free_per_user, "client": free_per_client}
        self.base_s, self.max_s, self.clock = base_s, max_s, clock
        self._failures: dict[tuple[str, str], tuple[int, float]] = {}  # key -> count, until
        self._last: dict[str, float] = {}  # user -> time of its last failure
        self._lock = threading.Lock()

    def wait_s(self, user: str, client: str, device: str | None = None) -> float:
        """Seconds until ``user`` may try again from ``client`` (0: now), or from their known
        ``device`` (whatever the address)."""
        now = self.clock()
        keys = [("client", client)] if device is None else [("device", f"{user}\n{device}")]
        with self._lock:
            if device is None and ("pair", f"{user}\n{client}") in self._failures:
                keys.append(("user", user))
            return max(0.0, *(self._failures.get(key, (0, 0.0))[1] - now for key in keys))

    def check(self, user: str, client: str, device: str | None = None) -> None:
        """Refuse ``user`` from ``client`` (from their known ``device``) while locked.

        Raises:
            LoginRefused: 429, with the seconds to wait.
        """
        wait = self.wait_s(user, client, device)
        if wait > 0:
            raise LoginRefused(429, f"too many failed logins; try again in {wait:.0f} s.",
                               wait)

    def failed(self, user: str, client: str, device: str | None = None) -> None:
        now = self.clock()
        with self._lock:
            if len(self._failures) > 100_000:  # bounded: forget the stale ones
                self._failures = {key: value for key, value in self._failures.items()
                                  if value[1] > now - self.max_s}
            if device is not None:  # the device's own count, nobody else's
                self._count(("device", f"{user}\n{device}"), "user", now)
                return
            if now - self._last.get(user, now) > 2 * self.max_s:  # quiet for long: forgotten
                self._failures.pop(("user", user), None)
            self._last[user] = now
            if len(self._last) > 100_000:
                self._last = {name: last for name, last in self._last.items()
                              if last > now - 2 * self.max_s}
            self._count(("user", user), "user", now)
            self._count(("client", client), "client", now)
            self._failures[("pair", f"{user}\n{client}")] = (1, now)

    def _count(self, key: tuple[str, str], free: str, now: float) -> None:
        count = self._failures.get(key, (0, 0.0))[0] + 1
        over = count - self.free[free]
        until = now + min(self.max_s, self.base_s * 2 ** (over - 1)) if over > 0 else 0.0
        self._failures[key] = (count, until)

    def succeeded(self, user: str, client: str, device: str | None = None) -> None:
        """A right password: clears the device's failures (from a known ``device``: it says
        nothing of the others on its address), else the address's failures for the name."""
        with self._lock:
            if device is not None:
                self._failures.pop(("device", f"{user}\n{device}"), None)
            else:
                self._failures.pop(("pair", f"{user}\n{client}"), None)


class LoginSlots:
    """Logins waiting for their password check: :data:`LOGINS_AT_ONCE` checked at a time,
    at most one per user name and client address waiting or being checked (see the module
    docstring). Used from one event loop.
    """

    def __init__(self, at_once: int = LOGINS_AT_ONCE):
        self.at_once = at_once
        self._pending: set[tuple[str, str]] = set()
        self._semaphore: asyncio.Semaphore | None = None

    @contextlib.asynccontextmanager
    async def slot(self, user: str, client: str) -> AsyncIterator[None]:
        """Wait for a turn to check ``user``'s password from ``client``.

        Raises:
            LoginRefused: 429, a login of ``user`` from ``client`` is waiting already.
        """
        key = (user, client)
        if key in self._pending:
            raise LoginRefused(429, f"a login of {user[:64]!r} from this address is under way; "
                               "wait for its answer.", 1.0)
        if self._semaphore is None:
            self._semaphore = asyncio.Semaphore(self.at_once)
        self._pending.add(key)
        try:
            async with self._semaphore:
                yield
        finally:
            self._pending.discard(key)
