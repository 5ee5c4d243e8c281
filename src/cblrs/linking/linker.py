"""Hand-over between planes: one global id for a track that passes from plane to plane.

Each plane's matcher numbers its own tracks. :class:`PlaneLinker` reads every plane's track
rows and gives each (plane, track) a **global id**: a track that starts where a link says
tracks arrive from a neighbouring plane (an overlap band, a portal; :mod:`cblrs.linking.links`)
takes the id of the neighbour's track it continues, if one fits; any other track gets a new id.

How it decides (each rule also in :class:`LinkerConfig`):

* **In time order, across planes.** Rows wait until every plane has passed their time (the
  caller's *watermark*: :meth:`PlaneLinker.advance`), then are taken in (time, plane, track)
  order, so the result depends only on the rows, never on how they arrived or were chunked.
* **Watch, then decide.** A track that starts in a hand-over region is watched for
  ``decision_s`` (1 s); then its candidates are scored on what was seen up to that instant:
  - *overlap* links: the neighbour's tracks seen at the same instants (within
    ``time_tolerance_s``): the mean distance between the two planes' rows, which must be
    under the link's ``max_distance_m``, plus ``velocity_weight_s`` x the difference of
    their velocities; a neighbour's track that ended just before (up to the link's
    ``transit_s``) is scored by where its last velocity would have taken it;
  - *portal* links: the neighbour's tracks that ended in the portal on their plane
    ``transit_s`` before; the time it took against the time the distance between the two
    portals' rows would take at the track's last speed, in units of ``max(1 s, 30 %)``
    (at most 3 of them);
  - the candidate must have the same class (when both are known), its global id must not
    already be on this plane at this instant, and it must be the latest track of its id.
  The lowest score wins; without a fitting candidate the track gets a new id.
* **One row per id and instant.** Where two planes both see a person (an overlap band) the
  global track takes the row of the plane that sees it deepest inside its rectangle.
* **Bounded delay.** Rows leave in time order once no track before them is still being
  watched: at most ``decision_s`` after the watermark passed them.

State (tracks being watched, recent tracks of every plane, rows not yet out, the next id)
is JSON (:meth:`PlaneLinker.get_state` / :meth:`PlaneLinker.set_state`), so a linker service
that restarts resumes exactly; tracks unseen for ``forget_after_s`` are forgotten.

Example:
    >>> from cblrs.plane import PlaneSet, PlaneSpec
    >>> planes = PlaneSet([PlaneSpec(1, (0, 0), 40, 30), PlaneSpec(2, (34, 0), 40, 30)])
    >>> linker = PlaneLinker(planes, [PlaneLink.overlap(planes[0], planes[1])])
    >>> times = np.arange(0, 10, 0.1)
    >>> walk = np.c_[30 + 1.2 * times, np.full(len(times), 10.0)]   # west to east at 1.2 m/s
    >>> on_1, on_2 = walk[:, 0] <= 40, walk[:, 0] >= 34
    >>> def rows(mask, track): return Tracks(np.flatnonzero(mask), times[mask],
    ...                                      np.full(mask.sum(), track), walk[mask])
    >>> linker.push(1, rows(on_1, 7)), linker.push(2, rows(on_2, 3))  # none of them late
    (0, 0)
    >>> linked = linker.finish()
    >>> sorted(set(linked.tracks.track_id.tolist())), len(linked.tracks) == len(times)
    ([1], True)
"""

from __future__ import annotations

import bisect
import heapq
import logging
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import Tracks
from cblrs.linking.links import PlaneLink
from cblrs.linking.scoring import LinkerConfig, overlap_score, portal_score
from cblrs.plane import PlaneSet

logger = logging.getLogger(__name__)

STATE_VERSION = "cblrs.linker-state/1"

# One row inside the linker: (time, plane, local track, frame, x, y, class).
Row = tuple[float, int, int, int, float, float, int]


@dataclass(frozen=True)
class Handover:
    """A track that continued another plane's track under its global id.

    Attributes:
        global_id: the id both tracks carry.
        timestamp: when the new track started (seconds).
        from_plane, from_track: the earlier track.
        to_plane, to_track: the track that continued it.
        kind: ``"overlap"`` or ``"portal"``.
        score: the winning score (lower is better; see the module docstring).
    """

    global_id: int
    timestamp: float
    from_plane: int
    from_track: int
    to_plane: int
    to_track: int
    kind: str
    score: float


@dataclass(frozen=True, eq=False)
class LinkedRows:
    """Global track rows, in time order, with where each came from.

    Attributes:
        tracks: the rows; ``track_id`` is the global id, ``camera_id`` -1.
        plane_id: (N,) int64 the plane whose matcher gave each row.
        local_track_id: (N,) int64 that matcher's track id.
    """

    tracks: Tracks
    plane_id: NDArray[np.int64]
    local_track_id: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.tracks)

    @classmethod
    def empty(cls) -> LinkedRows:
        """No rows."""
        return cls(Tracks.empty(), np.zeros(0, np.int64), np.zeros(0, np.int64))

    @classmethod
    def concatenate(cls, parts: Sequence[LinkedRows]) -> LinkedRows:
        """All rows of ``parts``, in order."""
        if not parts:
            return cls.empty()
        return cls(Tracks.concatenate([part.tracks for part in parts]),
                   np.concatenate([part.plane_id for part in parts]),
                   np.concatenate([part.local_track_id for part in parts]))


@dataclass
class _Local:
    """One plane's track as the linker knows it."""

    plane: int
    track: int
    class_id: int
    first_t: float
    first_xy: tuple[float, float]
    last_t: float
    last_xy: tuple[float, float]
    global_id: int | None = None
    decide_at: float | None = None
    history: list[tuple[float, float, float]] = field(default_factory=list)  # (t, x, y)
    held: list[Row] = field(default_factory=list)


class PlaneLinker:
    """Global ids across planes from every plane's track rows (see the module docstring).

    Args:
        planes: the site's planes (a row's depth inside its plane picks the row shown where
            two planes overlap).
        links: the hand-overs between planes.
        config: the rules' settings.
    """

    def __init__(self, planes: PlaneSet, links: Iterable[PlaneLink],
                 config: LinkerConfig | None = None):
        self.planes = planes
        self.links = tuple(links)
        self.config = config or LinkerConfig()
        for link in self.links:
            for plane_id in link.planes:
                planes.by_id(plane_id)
        self._links_of: dict[int, list[PlaneLink]] = defaultdict(list)
        for link in self.links:
            for plane_id in link.planes:
                self._links_of[plane_id].append(link)
        self._history_s = (self.config.decision_s + self.config.velocity_window_s
                           + 2 * self.config.time_tolerance_s)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget every track, every row and every id."""
        self.clock = -math.inf          # every row at or before it has been taken
        self.emitted_until = -math.inf  # every row at or before it has left
        self.next_id = 1
        self.counters: dict[str, int] = defaultdict(int)
        self._inbox: dict[int, list[Row]] = defaultdict(list)
        self._locals: dict[tuple[int, int], _Local] = {}
        self._on_plane: dict[int, dict[tuple[int, int], _Local]] = defaultdict(dict)
        self._watch: list[tuple[float, int, int]] = []  # (decide_at, plane, track), sorted
        self._last_forget = -math.inf
        self._by_global: dict[int, list[tuple[int, int]]] = defaultdict(list)
        # Rows with their id, waiting to leave: a heap of (time, global id, plane, track, row).
        self._out: list[tuple[float, int, int, int, Row]] = []
        self._handovers: list[Handover] = []

    def get_state(self) -> dict[str, Any]:
        """Everything the linker holds, as JSON-ready data (:meth:`set_state` restores it)."""
        return {
            "version": STATE_VERSION,
            "clock": _finite_or_none(self.clock),
            "emitted_until": _finite_or_none(self.emitted_until),
            "last_forget": _finite_or_none(self._last_forget),
            "next_id": self.next_id,
            "counters": dict(self.counters),
            "inbox": {str(plane): [list(row) for row in rows]
                      for plane, rows in self._inbox.items() if rows},
            "locals": [
                {**{key: value for key, value in asdict(local).items()
                    if key not in ("history", "held")},
                 "history": [list(item) for item in local.history],
                 "held": [list(row) for row in local.held]}
                for local in self._locals.values()
            ],
            "out": [[list(item[4]), item[1]] for item in sorted(self._out)],
            "handovers": [asdict(item) for item in self._handovers],
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`get_state` data (ValueError for another format)."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise ValueError(f"not a linker state of version {STATE_VERSION}")
        self.reset()
        self.clock = _or_minus_infinity(state["clock"])
        self.emitted_until = _or_minus_infinity(state["emitted_until"])
        self.next_id = int(state["next_id"])
        self.counters.update({key: int(value) for key, value in state["counters"].items()})
        for plane, rows in state["inbox"].items():
            self._inbox[int(plane)] = [_row(row) for row in rows]
        for item in state["locals"]:
            local = _Local(
                plane=int(item["plane"]), track=int(item["track"]),
                class_id=int(item["class_id"]), first_t=float(item["first_t"]),
                first_xy=(float(item["first_xy"][0]), float(item["first_xy"][1])),
                last_t=float(item["last_t"]),
                last_xy=(float(item["last_xy"][0]), float(item["last_xy"][1])),
                global_id=None if item["global_id"] is None else int(item["global_id"]),
                decide_at=None if item["decide_at"] is None else float(item["decide_at"]),
                history=[(float(t), float(x), float(y)) for t, x, y in item["history"]],
                held=[_row(row) for row in item["held"]],
            )
            key = (local.plane, local.track)
            self._locals[key] = local
            self._on_plane[local.plane][key] = local
            if local.global_id is not None:
                self._by_global[local.global_id].append(key)
            else:
                assert local.decide_at is not None
                bisect.insort(self._watch, (local.decide_at, local.plane, local.track))
        self._last_forget = _or_minus_infinity(state.get("last_forget"))
        for row, global_id in state["out"]:
            self._emit(_row(row), int(global_id))
        self._handovers = [Handover(**item) for item in state["handovers"]]

    # ------------------------------------------------------------------ input
    def push(self, plane_id: int, tracks: Tracks) -> int:
        """Take a plane's rows (any chunk, each plane's in time order); returns how many were
        late (at or before rows already taken: counted as ``late_rows``, not linked)."""
        if len(tracks) == 0:
            return 0
        self.planes.by_id(plane_id)
        times = tracks.timestamp
        late = times <= self.clock
        if late.any():
            count = int(late.sum())
            self.counters["late_rows"] += count
            logger.warning("plane %d: %d rows came after their time was linked; not linked",
                           plane_id, count)
        kept = tracks[~late] if late.any() else tracks
        plane = int(plane_id)
        self._inbox[plane_id].extend(zip(
            kept.timestamp.tolist(), [plane] * len(kept), kept.track_id.tolist(),
            kept.frame.tolist(), kept.world_xy[:, 0].tolist(), kept.world_xy[:, 1].tolist(),
            kept.class_id.tolist(), strict=True))
        self.counters["rows_in"] += len(kept)
        return int(late.sum())

    def advance(self, watermark: float) -> LinkedRows:
        """Every plane's rows up to ``watermark`` (seconds) are in: link them and return the
        global rows that are final (in time order)."""
        if watermark <= self.clock:
            return self._flush(self.clock)
        taken: list[Row] = []
        for plane, rows in self._inbox.items():
            if not rows:
                continue
            ready = [row for row in rows if row[0] <= watermark]
            if ready:
                taken.extend(ready)
                self._inbox[plane] = [row for row in rows if row[0] > watermark]
        taken.sort(key=lambda row: (row[0], row[1], row[2]))
        for row in taken:
            self._decide_before(row[0])
            self._take(row)
        self.clock = watermark
        self._decide_until(watermark)
        self._forget(watermark)
        return self._flush(watermark)

    def finish(self) -> LinkedRows:
        """Every stream has ended: decide everything and return every row left."""
        last = [row[0] for rows in self._inbox.values() for row in rows]
        result = self.advance(max(last)) if last else LinkedRows.empty()
        self._decide_until(math.inf)
        return LinkedRows.concatenate([result, self._flush(math.inf)])

    def take_handovers(self) -> list[Handover]:
        """The hand-overs decided since the last call (oldest first)."""
        handovers, self._handovers = self._handovers, []
        return handovers

    def global_id_of(self, plane_id: int, track_id: int) -> int | None:
        """The global id of a plane's track (None: unknown, forgotten or not yet decided)."""
        local = self._locals.get((plane_id, track_id))
        return None if local is None else local.global_id

    @property
    def watching(self) -> int:
        """Tracks being watched before their id is decided."""
        return len(self._watch)

    @property
    def output_watermark(self) -> float:
        """Every global row before this time has left (-inf before any): the first watched
        track's start while one is watched, else the watermark."""
        if self._watch:
            return min(self._locals[(plane, track)].first_t for _, plane, track in self._watch)
        return self.clock

    @property
    def known_tracks(self) -> int:
        """Tracks of every plane the linker keeps (until ``forget_after_s`` after their last
        row)."""
        return len(self._locals)

    # ------------------------------------------------------------------ rows
    def _take(self, row: Row) -> None:
        time, plane, track, _, x, y, class_id = row
        key = (plane, track)
        local = self._locals.get(key)
        if local is None:
            local = _Local(plane, track, class_id, time, (x, y), time, (x, y))
            self._locals[key] = local
            self._on_plane[plane][key] = local
            if self._in_any_region(plane, (x, y)):
                local.decide_at = time + self.config.decision_s
                bisect.insort(self._watch, (local.decide_at, plane, track))
                self.counters["watched"] += 1
            else:
                self._assign(local, self._new_id())
        local.last_t, local.last_xy = time, (x, y)
        if local.class_id < 0 <= class_id:
            local.class_id = class_id
        history = local.history
        history.append((time, x, y))
        horizon = time - self._history_s
        if history[0][0] < horizon:
            # Rows arrive in time order: the old ones are at the front.
            cut = 1
            while cut < len(history) and history[cut][0] < horizon:
                cut += 1
            del history[:cut]
        if local.global_id is None:
            local.held.append(row)
        else:
            self._emit(row, local.global_id)

    def _in_any_region(self, plane: int, xy: tuple[float, float]) -> bool:
        point = np.array([xy])
        return any(bool(link.in_region(plane, point)[0]) for link in self._links_of.get(plane, ()))

    def _new_id(self) -> int:
        global_id = self.next_id
        self.next_id += 1
        return global_id

    def _assign(self, local: _Local, global_id: int) -> None:
        local.global_id = global_id
        local.decide_at = None
        self._by_global[global_id].append((local.plane, local.track))
        for row in local.held:
            self._emit(row, global_id)
        local.held = []

    def _forget(self, now: float) -> None:
        # Now and then, not at every call: a forgotten track is long past any candidacy
        # (forget_after_s >> transit + decision), so when does not change any decision.
        if now < self._last_forget + 0.1 * self.config.forget_after_s:
            return
        self._last_forget = now
        horizon = now - self.config.forget_after_s
        stale = [key for key, local in self._locals.items()
                 if local.last_t < horizon and local.global_id is not None]
        for key in stale:
            local = self._locals.pop(key)
            del self._on_plane[local.plane][key]
            keys = self._by_global.get(local.global_id or 0)
            if keys is not None:
                keys.remove(key)
                if not keys:
                    del self._by_global[local.global_id or 0]

    # ------------------------------------------------------------------ decisions
    def _decide_before(self, time: float) -> None:
        while self._watch and self._watch[0][0] < time:
            _, plane, track = self._watch.pop(0)
            self._decide(self._locals[(plane, track)])

    def _decide_until(self, time: float) -> None:
        while self._watch and self._watch[0][0] <= time:
            _, plane, track = self._watch.pop(0)
            self._decide(self._locals[(plane, track)])

    def _decide(self, new: _Local) -> None:
        assert new.decide_at is not None
        limit = new.decide_at
        best: tuple[float, int, int, str] | None = None  # (score, plane, track, kind)
        for link in self._links_of.get(new.plane, ()):
            if not bool(link.in_region(new.plane, np.array([new.first_xy]))[0]):
                continue
            other = link.other(new.plane)
            for candidate in self._candidates(new, other, link):
                if link.portal:
                    score = portal_score(candidate.plane, new.first_t, new.first_xy,
                                         candidate.last_t,
                                         candidate.last_xy, candidate.history, link, self.config)
                else:
                    score = overlap_score(
                        [item for item in new.history if item[0] <= limit],
                        [item for item in candidate.history if item[0] <= limit],
                        new.first_t, new.first_xy, candidate.last_t, candidate.last_xy,
                        link, self.config)
                if score is None:
                    continue
                item = (score, candidate.plane, candidate.track,
                        "portal" if link.portal else "overlap")
                if best is None or item < best:
                    best = item
        if best is None:
            self._assign(new, self._new_id())
            self.counters["new_ids"] += 1
            return
        score, plane, track, kind = best
        previous = self._locals[(plane, track)]
        assert previous.global_id is not None
        self._handovers.append(Handover(previous.global_id, new.first_t, plane, track,
                                        new.plane, new.track, kind, float(score)))
        self.counters[f"handovers_{kind}"] += 1
        self._assign(new, previous.global_id)

    def _candidates(self, new: _Local, plane: int, link: PlaneLink) -> list[_Local]:
        earliest = new.first_t - link.transit_s[1] - self.config.time_tolerance_s
        found = []
        for local in self._on_plane[plane].values():
            if (local.global_id is None or local.last_t < earliest
                    or local.first_t > new.decide_at):  # type: ignore[operator]
                continue
            if local.class_id >= 0 and new.class_id >= 0 and local.class_id != new.class_id:
                continue
            siblings = [self._locals[key] for key in self._by_global[local.global_id]
                        if key != (local.plane, local.track)]
            # The id is on the new track's plane at this instant already: not this one.
            if any(sibling.plane == new.plane
                   and sibling.last_t >= new.first_t - self.config.time_tolerance_s
                   for sibling in siblings):
                continue
            # The id went on elsewhere after this track: it is not the id's latest track.
            if any(sibling.first_t > local.last_t + self.config.time_tolerance_s
                   for sibling in siblings):
                continue
            found.append(local)
        return found

    # ------------------------------------------------------------------ output
    def _emit(self, row: Row, global_id: int) -> None:
        heapq.heappush(self._out, (row[0], global_id, row[1], row[2], row))

    def _flush(self, watermark: float) -> LinkedRows:
        out = self._out
        ready = []
        if self._watch:
            # Nothing at or after the first watched track's start leaves before its id.
            first = min(self._locals[(plane, track)].first_t for _, plane, track in self._watch)
            while out and out[0][0] < first:
                ready.append(heapq.heappop(out))
        else:
            while out and out[0][0] <= watermark:
                ready.append(heapq.heappop(out))
        if not ready:
            return LinkedRows.empty()
        # In (time, id, plane) order: the rows of one id and instant are neighbours.
        items: list[tuple[float, int, Row]] = []
        best_depth = -math.inf
        for time, global_id, _, _, row in ready:
            depth = self._depth(row)
            if items and items[-1][0] == time and items[-1][1] == global_id:
                if depth > best_depth:  # ties keep the lower plane (first in order)
                    items[-1] = (time, global_id, row)
                    best_depth = depth
                continue
            items.append((time, global_id, row))
            best_depth = depth
        self.counters["rows_out"] += len(items)
        self.counters["rows_shared"] += len(ready) - len(items)
        self.emitted_until = max(self.emitted_until, items[-1][0])
        return LinkedRows(
            tracks=Tracks(
                frame=np.array([row[3] for _, _, row in items], np.int64),
                timestamp=np.array([time for time, _, _ in items], np.float64),
                track_id=np.array([global_id for _, global_id, _ in items], np.int64),
                world_xy=np.array([(row[4], row[5]) for _, _, row in items],
                                  np.float64).reshape(-1, 2),
                class_id=np.array([row[6] for _, _, row in items], np.int64),
            ),
            plane_id=np.array([row[1] for _, _, row in items], np.int64),
            local_track_id=np.array([row[2] for _, _, row in items], np.int64),
        )

    def _depth(self, row: Row) -> float:
        plane = self.planes.by_id(row[1])
        x, y = row[4] - plane.origin[0], row[5] - plane.origin[1]
        return min(x, plane.width - x, y, plane.length - y)


def _row(values: Sequence[Any]) -> Row:
    return (float(values[0]), int(values[1]), int(values[2]), int(values[3]),
            float(values[4]), float(values[5]), int(values[6]))


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _or_minus_infinity(value: float | None) -> float:
    return -math.inf if value is None else float(value)


def link_tracks(
    planes: PlaneSet,
    links: Iterable[PlaneLink],
    per_plane: dict[int, Tracks],
    config: LinkerConfig | None = None,
) -> tuple[LinkedRows, list[Handover], dict[str, int]]:
    """Link whole files offline: every plane's tracks in, the global tracks out.

    The same :class:`PlaneLinker` a live linker runs, fed everything at once, so the result
    equals a live run on the same rows.

    Returns:
        ``(rows, handovers, counters)``.
    """
    linker = PlaneLinker(planes, links, config)
    for plane_id, tracks in sorted(per_plane.items()):
        order = np.argsort(tracks.timestamp, kind="stable")
        linker.push(plane_id, tracks[order])
    rows = linker.finish()
    return rows, linker.take_handovers(), dict(linker.counters)
