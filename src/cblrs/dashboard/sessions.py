"""The dashboard's open sessions: a table bounded per user and in all.

A session costs memory until it ends (logout, lifetime, idle time). Any user may log in as
often as scrypt lets them (failed logins back off, successful ones do not), so the table must
not let one user's logins end anyone else's session:

* a user holds at most ``per_user`` sessions: the next login of theirs ends their own session
  idle the longest (and first any that are expired, or opened before their record changed);
* in all there are at most ``most`` sessions: at that number, once the expired ones are gone,
  a new login is refused (:class:`SessionsFull`) rather than ending another user's session;
  an admin's is not refused (admins are few, each bounded by ``per_user``; a crowd of viewers
  must not keep every admin out).

Before, the table held 10,000 sessions in all and, full, ended the one idle the longest
whoever it belonged to: a viewer logging in 10,000 times ended the admin's session.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

from cblrs.dashboard.users import Role

if TYPE_CHECKING:
    from cblrs.dashboard.auth import Identity


class SessionsFull(Exception):
    """The table holds its most sessions and none of them may end for this login."""


class SessionTable:
    """Open sessions by id, with each user's ids (see the module docstring).

    Args:
        most: sessions in all (past it, a viewer's login is refused).
        per_user: sessions of one user (past it, their own idle-longest session ends).
        expired: whether a session has expired (its lifetime or idle time is over).
    """

    def __init__(self, most: int, per_user: int, expired: Callable[[Identity], bool]):
        if most < 1 or per_user < 1:
            raise ValueError("the session limits must be at least 1.")
        self.most, self.per_user, self.expired = most, per_user, expired
        self._by_id: dict[str, Identity] = {}
        self._by_user: dict[str, set[str]] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._by_id)

    def get(self, session_id: str) -> Identity | None:
        with self._lock:
            return self._by_id.get(session_id)

    def count(self, user: str) -> int:
        """How many sessions ``user`` holds (expired ones included until they are dropped)."""
        with self._lock:
            return len(self._by_user.get(user, ()))

    def drop(self, session_id: str) -> None:
        """End a session (nothing if it has ended already)."""
        with self._lock:
            self._drop(session_id)

    def drop_if(self, identity: Identity) -> bool:
        """End ``identity``'s session if it is still the open one and has expired; whether it
        is still open (and not expired)."""
        with self._lock:
            if self._by_id.get(identity.session or "") is not identity:
                return False
            if self.expired(identity):
                self._drop(identity.session or "")
                return False
            return True

    def add(self, identity: Identity) -> list[Identity]:
        """Open ``identity``'s session; the user's own sessions it ended to make room.

        Raises:
            SessionsFull: at :attr:`most` sessions (none expired), not an admin's, and the
                user below :attr:`per_user` (at it, their login replaces their own session).
        """
        assert identity.session is not None
        with self._lock:
            mine = []
            for key in list(self._by_user.get(identity.user, ())):
                other = self._by_id[key]
                if self.expired(other) or other.stamp != identity.stamp:
                    self._drop(key)  # over already, or opened before the record changed
                else:
                    mine.append(other)
            mine.sort(key=lambda other: other.last_seen)
            ended = mine[:max(0, len(mine) - self.per_user + 1)]
            if not ended and len(self._by_id) >= self.most:
                for key, other in list(self._by_id.items()):
                    if self.expired(other):
                        self._drop(key)
                if len(self._by_id) >= self.most and identity.role < Role.ADMIN:
                    raise SessionsFull(f"the dashboard holds {self.most} sessions, the most "
                                       "it keeps; try again when some have ended.")
            for other in ended:
                self._drop(other.session or "")
            self._by_id[identity.session] = identity
            self._by_user.setdefault(identity.user, set()).add(identity.session)
        return ended

    def _drop(self, session_id: str) -> None:
        identity = self._by_id.pop(session_id, None)
        if identity is None:
            return
        mine = self._by_user.get(identity.user)
        if mine is not None:
            mine.discard(session_id)
            if not mine:
                del self._by_user[identity.user]
