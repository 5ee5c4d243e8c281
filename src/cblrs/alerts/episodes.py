"""Alert episodes: each fires once when its condition has held long enough, clears once.

:class:`AlertEpisodes` is fed :class:`Observation` s of a plane (what the matcher knows after
each tracker batch: occupancy, open visits, crossings, cameras, lag) and returns the
:class:`AlertEvent` s they cause. Per rule and subject (the zone, line or camera; one subject
for the matcher's lag) it keeps one small state machine::

    quiet --condition--> pending (since t) --held for_s--> firing: "fired" --not--> quiet: "cleared"

A condition that stops before ``for_s`` fires nothing. Every episode has an id
(``rule/subject/n``) that stays with its "fired" and its "cleared"; the state
(:meth:`AlertEpisodes.get_state`) is JSON, so a restarted matcher that restores it neither
fires an open episode again nor forgets to clear it. Time is the observations' own (capture
time), so a replay alerts as the live run did.

With the site's opening hours (a :class:`cblrs.localtime.LocalCalendar`), the rules about
places — occupancy, dwell, line_count — hold no breach while the site is closed: nothing
fires after closing, an episode firing at closing time clears at the first observation
after it, and a condition still true at opening starts its ``for_s`` afresh. Camera and
matcher rules watch the system, not the public, and run at every hour.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from cblrs.alerts.rules import (
    AlertsModel,
    CameraOfflineRule,
    DwellRule,
    LineCountRule,
    MatcherLagRule,
    OccupancyRule,
)
from cblrs.errors import CblrsError

STATE_VERSION = "cblrs.alert-episodes/1"
_PLACE_RULES = (OccupancyRule, DwellRule, LineCountRule)
_MATCHER = "matcher"


@dataclass(frozen=True)
class Observation:
    """What a plane looks like at ``timestamp`` (seconds).

    Attributes:
        timestamp: the observation's time (the matcher's released capture time), seconds.
        occupancy: zone -> confirmed tracks inside now.
        longest_visit_s: zone -> the longest open visit's dwell so far, seconds.
        crossings: ``(line, direction, timestamp)`` of the crossings counted since the last
            observation.
        camera_silence_s: camera -> seconds since its last message (None: never heard).
        cameras_offline: cameras that said they are offline (their last will or a clean end).
        lag_s: the tracker's lag behind capture time, seconds (None: unknown).
    """

    timestamp: float
    occupancy: Mapping[str, int] = field(default_factory=dict)
    longest_visit_s: Mapping[str, float] = field(default_factory=dict)
    crossings: tuple[tuple[str, str, float], ...] = ()
    camera_silence_s: Mapping[str, float | None] = field(default_factory=dict)
    cameras_offline: frozenset[str] = frozenset()
    lag_s: float | None = None


@dataclass(frozen=True)
class AlertEvent:
    """An episode fired or cleared.

    Attributes:
        episode: ``rule/subject/n``: the same for an episode's "fired" and "cleared" (a
            receiver de-duplicates on ``(episode, state)``).
        rule, kind: the rule's name and kind.
        subject: the zone, line or camera ("matcher" for the lag).
        state: ``"fired"`` or ``"cleared"``.
        timestamp: when (the observation's time; for "fired", when the condition began is
            ``since``), seconds.
        since: when the condition began, seconds.
        value: the measured value (tracks, seconds, crossings).
        threshold: the rule's threshold.
    """

    episode: str
    rule: str
    kind: str
    subject: str
    state: str
    timestamp: float
    since: float
    value: float
    threshold: float

    def to_dict(self) -> dict[str, Any]:
        """The event as JSON-ready data (``schema`` ``cblrs.alert/1``)."""
        return {"schema": "cblrs.alert/1", **asdict(self)}


@dataclass
class _Episode:
    pending_since: float | None = None
    firing: bool = False
    count: int = 0
    value: float = 0.0


class AlertEpisodes:
    """The alert state of one plane: rules in, fired and cleared events out."""

    def __init__(self, alerts: AlertsModel, calendar: Any = None) -> None:
        self.rules = list(alerts.rules)
        self.calendar = calendar
        self.reset()

    def reset(self) -> None:
        """Forget every episode and window."""
        self._episodes: dict[tuple[str, str], _Episode] = {}
        self._windows: dict[str, deque[float]] = {
            rule.name: deque() for rule in self.rules if isinstance(rule, LineCountRule)
        }
        self.clock = -math.inf

    def observe(self, observation: Observation) -> list[AlertEvent]:
        """Advance to ``observation``; the events it causes, in rule order.

        An observation older than the last is ignored (the episodes only move forward).
        """
        now = observation.timestamp
        if now < self.clock:
            return []
        self.clock = now
        closed = self.calendar is not None and not self.calendar.is_open(now)
        events: list[AlertEvent] = []
        for rule in self.rules:
            threshold, hold, measured = self._measure(rule, observation)
            quiet = closed and isinstance(rule, _PLACE_RULES)
            for subject, value in measured.items():
                events += self._step(rule, subject, value, value > threshold and not quiet,
                                     hold, now, threshold)
        return events

    def _measure(
        self, rule: Any, seen: Observation
    ) -> tuple[float, float, dict[str, float]]:
        """(threshold, how long the breach must hold, subject -> value) of a rule."""
        if isinstance(rule, OccupancyRule):
            return rule.above, rule.for_s, {rule.zone: float(seen.occupancy.get(rule.zone, 0))}
        if isinstance(rule, DwellRule):
            return rule.above_s, 0.0, {rule.zone: float(seen.longest_visit_s.get(rule.zone, 0))}
        if isinstance(rule, LineCountRule):
            window = self._windows[rule.name]
            for line, direction, timestamp in seen.crossings:
                if line == rule.line and rule.direction in ("both", direction):
                    window.append(timestamp)
            while window and window[0] <= seen.timestamp - rule.per_s:
                window.popleft()
            return rule.above, 0.0, {rule.line: float(len(window))}
        if isinstance(rule, CameraOfflineRule):
            cameras = [rule.camera] if rule.camera is not None else sorted(
                set(seen.camera_silence_s) | set(seen.cameras_offline))
            values = {}
            for camera in cameras:
                silence = seen.camera_silence_s.get(camera)
                offline = camera in seen.cameras_offline or silence is None or silence > 10.0
                # The value is "offline" (1) or not (0); how long it must last is for_s.
                values[camera] = 1.0 if offline else 0.0
            return 0.5, rule.for_s, values
        assert isinstance(rule, MatcherLagRule)
        lag = seen.lag_s if seen.lag_s is not None else 0.0
        return rule.above_s, rule.for_s, {_MATCHER: float(lag)}

    def _step(self, rule: Any, subject: str, value: float, breach: bool, hold: float,
              now: float, threshold: float) -> list[AlertEvent]:
        key = (rule.name, subject)
        episode = self._episodes.setdefault(key, _Episode())
        if not breach:
            since, episode.pending_since = episode.pending_since, None
            if not episode.firing:
                return []
            episode.firing = False
            return [self._event(rule, subject, episode, "cleared", now, value, threshold,
                                since)]
        if episode.pending_since is None:
            episode.pending_since = now
        episode.value = max(episode.value, value) if episode.firing else value
        if episode.firing or now - episode.pending_since < hold:
            return []
        episode.firing = True
        episode.count += 1
        return [self._event(rule, subject, episode, "fired", now, value, threshold,
                            episode.pending_since)]

    def _event(self, rule: Any, subject: str, episode: _Episode, state: str, now: float,
               value: float, threshold: float, since: float | None) -> AlertEvent:
        since = now if since is None else since
        return AlertEvent(
            episode=f"{rule.name}/{subject}/{episode.count}", rule=rule.name, kind=rule.kind,
            subject=subject, state=state, timestamp=now, since=since, value=value,
            threshold=threshold,
        )

    def firing(self) -> list[tuple[str, str]]:
        """``(rule, subject)`` of the episodes firing now."""
        return [key for key, episode in self._episodes.items() if episode.firing]

    def active(self) -> list[dict[str, Any]]:
        """The episodes firing now: episode, rule, kind, subject, since, value."""
        kinds = {rule.name: rule.kind for rule in self.rules}
        return [
            {"episode": f"{rule}/{subject}/{episode.count}", "rule": rule,
             "kind": kinds.get(rule, ""), "subject": subject,
             "since": episode.pending_since, "value": episode.value}
            for (rule, subject), episode in self._episodes.items() if episode.firing
        ]

    # ------------------------------------------------------------------ persistence
    def get_state(self) -> dict[str, Any]:
        """Everything needed to go on after a restart, as JSON-ready data."""
        return {
            "version": STATE_VERSION,
            "rules": [rule.model_dump(mode="json") for rule in self.rules],
            "clock": None if math.isinf(self.clock) else self.clock,
            "episodes": [[rule, subject, asdict(episode)]
                         for (rule, subject), episode in self._episodes.items()],
            "windows": {name: list(window) for name, window in self._windows.items()},
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`get_state`. Episodes of rules that changed since start afresh.

        Raises:
            CblrsError: not such a state.
        """
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise CblrsError(f"not a saved alert state (expected {STATE_VERSION}).")
        self.reset()
        saved = {rule["name"]: rule for rule in state.get("rules", [])}
        same = {rule.name for rule in self.rules
                if saved.get(rule.name) == rule.model_dump(mode="json")}
        self.clock = -math.inf if state.get("clock") is None else float(state["clock"])
        for rule, subject, episode in state.get("episodes", []):
            if rule in same:
                self._episodes[(rule, subject)] = _Episode(**episode)
        for name, times in (state.get("windows") or {}).items():
            if name in same and name in self._windows:
                self._windows[name].extend(float(value) for value in times)


def events_of(items: Iterable[dict[str, Any]]) -> list[AlertEvent]:
    """Alert events from their :meth:`AlertEvent.to_dict` data."""
    return [AlertEvent(**{key: value for key, value in item.items() if key != "schema"})
            for item in items]
