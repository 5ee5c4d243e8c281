"""Repair after assignment (step 7 of the fusion tracker's update): two people whose tracks
swapped while they passed close get their ids back.

In a crowd two people pass within a few decimetres of each other; their views overlap, the
assignment of one instant takes the wrong pairing, and each track goes on with the other
person (the crowd's main identity error). At that instant the pairing is a coin toss; a
second later, when they are apart again, it is not: each track's motion before the encounter
predicts one of the two people after it far better than the other. This stage takes that
decision later, once the evidence is in:

* an **encounter** opens when two confirmed tracks of people (classes that turn on the spot:
  vehicles have the motion check) come within ``swap_radius_m`` of each other. From then
  on the stage records, per instant, both tracks' filter states after the update and the
  position their views were fused to (none when unseen);
* it closes when they have been farther apart than that for ``swap_settle_s`` (or after
  ``_LONGEST_S``; it is dropped when a track ends). The stage then asks, for every instant
  ``k`` of the encounter, whether the tracks would explain what was seen from ``k`` on
  better swapped: each track's filter state before ``k`` is run, with the tracker's motion
  models, through its own fused positions and through the other track's, and the
  log-likelihoods of the innovations are summed (``keep`` and ``swap``). (The runs are
  advanced as the instants come, all encounters together, and a track's run through its
  own views is its own filter: see :meth:`SwapCheck._advance`; the sums are the replay's.)
* if for some ``k`` the swapped pairing is more likely by ``swap_margin`` (log units; the
  default 7 is odds of about 1,100 to 1), the two tracks exchange ids from now on.

Nothing else moves: the filters stay with the views they took (they follow the people they
follow), and ids once reported are never rewritten; the rows reported between the swap and
the decision (about ``swap_settle_s`` after the two are apart) keep the wrong ids. A
service restarted from the tracker's state continues the open encounters.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from cblrs.matching import kalman
from cblrs.matching.fusion.gaussian import close_pairs
from cblrs.matching.fusion.table import FusionContext, TrackTable

_LONGEST_S = 10.0  # an encounter still open after this long is decided then


@dataclass
class _Encounter:
    """Two tracks close together: per instant since it opened, each track's state and view.

    ``states[id]`` holds one (mode_state, mode_covariance, mode_probability) per instant
    from the opening one; ``views[id]`` one (xy, covariance) per later instant (NaN: unseen).
    """

    opened: float
    last: float
    apart_since: float | None = None
    steps: list[float] = field(default_factory=list)
    states: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = field(default_factory=dict)
    views: dict[int, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)
    serial: int = -1  # its runs in the stage's run table (-1: none, replayed when decided)
    sigma: np.ndarray | None = None  # the accelerations its runs were advanced with


class SwapCheck:
    """The swap stage of :class:`~cblrs.matching.fusion.tracker.FusionTracker`.

    The tracker gives it each instant's fused views (:meth:`observe`, after the filter
    update) and then asks which confirmed tracks exchange ids (:meth:`decide`). It changes
    neither the table nor its inputs.

    Args:
        context: the tracker's configuration and motion models.
        class_acceleration: (K + 1,) white-noise acceleration of each class slot, m/s^2
            (the tracker's; the motion models scale it).
    """

    def __init__(self, context: FusionContext, class_acceleration: np.ndarray):
        self.context = context
        self.class_acceleration = class_acceleration
        config = context.config
        self.enabled = config.swap_radius_m > 0
        self._factors = np.asarray(config.model_acceleration_factors, np.float64)
        self._sojourn = np.asarray(config.model_sojourn_s, np.float64)
        self._sigmas: dict[int, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """Forget every open encounter."""
        self._open: dict[tuple[int, int], _Encounter] = {}
        self._views: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._runs = _Runs.empty(len(self._sojourn))
        self._serial = 0
        self._previous: dict[int, int] = {}  # encounter: its first track's row in these
        self._previous_parts: tuple[np.ndarray, ...] = ()

    @property
    def open_count(self) -> int:
        """Encounters open now."""
        return len(self._open)

    def observe(
        self, ids: np.ndarray, fused_xy: np.ndarray, fused_covariance: np.ndarray, seen: np.ndarray
    ) -> None:
        """Each confirmed track's fused position at this instant (its views fused, plus the
        object noise the filter adds), for the encounters it is part of."""
        if not self.enabled:
            return
        rows = np.flatnonzero((ids >= 0) & seen).tolist()
        # Rows of the caller's arrays, not copies: the tracker makes them anew each instant
        # and never writes to them after.
        self._views = {
            one: (fused_xy[row], fused_covariance[row])
            for one, row in zip(ids[rows].tolist(), rows, strict=True)
        }

    def decide(self, tracks: TrackTable, timestamp: float) -> list[tuple[int, int]]:
        """Rows of tracks that exchange ids now: (row, row) pairs, no row twice.

        Records this instant in every open encounter, opens those of people newly close,
        and decides those that closed.
        """
        if not self.enabled:
            return []
        views, self._views = self._views, {}
        people = (tracks.ids >= 0) & ~np.isfinite(
            self.context.class_turn_radius[self.context.class_slot(tracks.class_id)]
        )
        row_of = {int(one): row for row, one in enumerate(tracks.ids.tolist()) if one >= 0}
        config = self.context.config
        swaps: list[tuple[int, int]] = []
        swapped: set[int] = set()
        gone: set[int] = set()  # encounters whose runs are no longer needed
        alive: list[tuple[tuple[int, int], _Encounter]] = []
        for key, encounter in list(self._open.items()):
            if key[0] in row_of and key[1] in row_of:
                alive.append((key, encounter))
            else:
                del self._open[key]  # a track ended: nothing to swap
                gone.add(encounter.serial)
        closed: list[tuple[tuple[int, int], _Encounter]] = []
        if alive:
            first_rows = np.array([row_of[key[0]] for key, _ in alive])
            second_rows = np.array([row_of[key[1]] for key, _ in alive])
            offset = tracks.state[first_rows, :2] - tracks.state[second_rows, :2]
            far = np.hypot(offset[:, 0], offset[:, 1]) > config.swap_radius_m
            for (key, encounter), apart in zip(alive, far.tolist(), strict=True):
                encounter.steps.append(timestamp - encounter.last)
                encounter.last = timestamp
                for one in key:
                    encounter.views[one].append(views.get(one, _UNSEEN))
                if not apart:
                    encounter.apart_since = None
                elif encounter.apart_since is None:
                    encounter.apart_since = timestamp
                settled = apart and timestamp - encounter.apart_since >= config.swap_settle_s
                if settled or timestamp - encounter.opened >= _LONGEST_S:
                    del self._open[key]
                    closed.append((key, encounter))
            self._advance(alive, tracks, np.column_stack([first_rows, second_rows]), views, gone)
        for key, encounter in closed:
            first, second = key
            if first in swapped or second in swapped or not encounter.steps:
                continue
            rows = [row_of[first], row_of[second]]
            if self._gain(encounter, key, tracks.class_id[rows[0]]) > config.swap_margin:
                swaps.append((rows[0], rows[1]))
                swapped.update(key)
        self._runs.drop(gone | {encounter.serial for _, encounter in closed})
        ids = tracks.ids
        if swaps:
            self._rename(swaps, tracks)
            ids = ids.copy()
            for a, b in swaps:
                ids[a], ids[b] = ids[b], ids[a]
        self._open_new(tracks, ids, people, timestamp)
        self._record(tracks, ids)
        return swaps

    def _sigma(self, class_id: int) -> np.ndarray:
        """(M,) white-noise acceleration of each motion model for a track of this class."""
        sigma = self._sigmas.get(class_id)
        if sigma is None:
            slot = self.context.class_slot(np.array([class_id]))[0]
            sigma = self._sigmas[class_id] = self.class_acceleration[slot] * self._factors
        return sigma

    def _record(self, tracks: TrackTable, ids: np.ndarray) -> None:
        """Each open encounter's two filter states now, under the ids the tracks carry after
        this instant's swaps (``ids``): its history, and where its next runs start."""
        self._previous = {}
        if not self._open:
            return
        row_of = {int(one): row for row, one in enumerate(ids.tolist()) if one >= 0}
        rows = np.array([row_of[one] for key in self._open for one in key])
        self._previous_parts = parts = (
            tracks.mode_state[rows],
            tracks.mode_covariance[rows],
            tracks.mode_probability[rows],
        )
        state, covariance, probability = parts
        for index, (key, encounter) in enumerate(self._open.items()):
            for side, one in enumerate(key):
                row = 2 * index + side
                encounter.states[one].append((state[row], covariance[row], probability[row]))
            if encounter.serial >= 0:
                self._previous[encounter.serial] = 2 * index

    def _advance(
        self,
        alive: list[tuple[tuple[int, int], _Encounter]],
        tracks: TrackTable,
        rows: np.ndarray,
        views: dict[int, tuple[np.ndarray, np.ndarray]],
        gone: set[int],
    ) -> None:
        """Advance the runs of the open encounters (``alive``, their tracks' ``rows``, (E, 2))
        by this instant's step, after starting those of each one's previous instant
        (``gone``: encounters whose runs are dropped first).

        The runs :meth:`swap_gain` would replay when an encounter is decided are the same
        filters, fed the same views in the same order: run here one step per instant, all
        encounters at once, they cost a handful of array operations per instant instead of
        one per step of each encounter decided. Only the runs through the other track's
        views are kept: a track's run through its own views from any instant is its own
        filter (the tracker runs the same models on the same views), as each instant's
        check finds by running it one step from the previous instant; its log-likelihood
        there is added to the runs that need it. An encounter where the check fails, whose
        accelerations changed (a track's class did) or restored from a saved state is
        replayed when decided.
        """
        online: list[int] = []
        start: list[int] = []
        sigmas: list[np.ndarray] = []
        owner: list[int] = []
        step_of: dict[int, float] = {}
        for index, ((key, encounter), class_id) in enumerate(
            zip(alive, tracks.class_id[rows[:, 0]].tolist(), strict=True)
        ):
            if encounter.serial < 0:
                continue
            sigma = self._sigma(class_id)
            if encounter.sigma is None:
                encounter.sigma = sigma
            elif sigma is not encounter.sigma and not np.array_equal(sigma, encounter.sigma):
                gone.add(encounter.serial)
                encounter.serial = -1
                continue
            online.append(index)
            step_of[encounter.serial] = encounter.steps[-1]
            start.append(self._previous[encounter.serial])
            sigmas.append(sigma)
            owner += key
        runs = self._runs
        runs.drop(gone)
        if not online:
            return
        # The new runs through the other's views, then each track's one step through its own.
        index = (np.array(start)[:, None] + _SIDES).ravel()
        serial = np.repeat(np.array(list(step_of), np.int64), 2)
        owner_ids = np.array(owner, np.int64)
        seen_ids = owner_ids.reshape(-1, 2)[:, ::-1].ravel()
        acceleration = np.repeat(np.array(sigmas), 2, axis=0)
        starts = [part[index] for part in self._previous_parts]
        runs.append(*starts, acceleration, serial, owner_ids, seen_ids)
        count = len(runs.total)
        state, covariance, probability = (
            np.concatenate([whole, part])
            for whole, part in zip(
                (runs.state, runs.covariance, runs.probability), starts, strict=True
            )
        )
        accelerations = np.concatenate([runs.acceleration, acceleration])
        ids, inverse = np.unique(np.concatenate([runs.seen, owner_ids]), return_inverse=True)
        picked = [views.get(one, _UNSEEN) for one in ids.tolist()]
        xy = np.stack([view[0] for view in picked])[inverse]
        view_covariance = np.stack([view[1] for view in picked])[inverse]
        gain = np.zeros(len(state))
        saw = np.zeros(len(state), dtype=bool)
        steps = sorted(set(step_of.values()))
        if len(steps) > 1:  # (all encounters are recorded at every instant: not seen so far)
            serials, where = np.unique(np.concatenate([runs.serial, serial]), return_inverse=True)
            row_step = np.array([step_of[one] for one in serials.tolist()])[where]
        for step in steps:
            part = np.arange(len(state))
            if len(steps) > 1:
                part = np.flatnonzero(row_step == step)
            new_state, new_covariance, new_probability, seen_now, log = _step(
                state[part],
                covariance[part],
                probability[part],
                step,
                xy[part],
                view_covariance[part],
                accelerations[part],
                self._sojourn,
            )
            state[part], covariance[part] = new_state, new_covariance
            probability[part] = new_probability
            gain[part[seen_now]] = log
            saw[part[seen_now]] = True
        runs.state, runs.covariance = state[:count], covariance[:count]
        runs.probability = probability[:count]
        runs.total[saw[:count]] += gain[:count][saw[:count]]
        # Each track's own filter now must be its one step from the previous instant.
        now = rows[online].ravel()
        same = (
            (state[count:] == tracks.mode_state[now]).all(axis=(1, 2))
            & (covariance[count:] == tracks.mode_covariance[now]).all(axis=(1, 2, 3))
            & (probability[count:] == tracks.mode_probability[now]).all(axis=1)
        )
        code = (serial << 32) | owner_ids
        order = np.argsort(code)
        probe = count + order[np.searchsorted(code[order], (runs.serial << 32) | runs.owner)]
        own = saw[probe]
        runs.keep[own] += gain[probe][own]
        failed = np.flatnonzero(~same.reshape(-1, 2).all(axis=1)).tolist()
        for one in failed:
            gone.add(alive[online[one]][1].serial)
            alive[online[one]][1].serial = -1
        runs.drop(gone)

    def _gain(self, encounter: _Encounter, key: tuple[int, int], class_id: int) -> float:
        """:meth:`swap_gain` from the runs advanced each instant (replayed if it has none)."""
        sigma = self._sigma(class_id)  # (the cached array itself while the class is the same)
        if encounter.serial < 0 or (sigma is not encounter.sigma
                                    and not np.array_equal(sigma, encounter.sigma)):
            return self.swap_gain(encounter, key, class_id)
        runs = self._runs
        mine = runs.serial == encounter.serial
        owner, total, keep = runs.owner[mine], runs.total[mine], runs.keep[mine]
        first, second = key
        # Per start: its two runs through the other's views and its tracks' own filters.
        return float(
            np.max(
                total[owner == first]
                + total[owner == second]
                - keep[owner == first]
                - keep[owner == second]
            )
        )

    def swap_gain(self, encounter: _Encounter, key: tuple[int, int], class_id: int) -> float:
        """The largest, over the encounter's instants, log-likelihood of the swapped pairing
        from that instant on minus that of the pairing the tracker kept (replayed from the
        recorded states and views)."""
        count = len(encounter.steps)
        sigma = self._sigma(class_id)
        # Four runs per start instant: each track's filter through its own views and
        # through the other's, batched (B = 4 x instants).
        owners = [key[0], key[1], key[0], key[1]]
        seen = [key[0], key[1], key[1], key[0]]
        state, covariance, probability = (
            np.concatenate(
                [
                    np.stack([one[part] for one in encounter.states[owner][:count]])
                    for owner in owners
                ]
            )
            for part in range(3)
        )
        xy = np.stack(
            [np.stack([view[0] for view in encounter.views[one]]) for one in seen], axis=1
        )  # (S, 4, 2)
        view_covariance = np.stack(
            [np.stack([view[1] for view in encounter.views[one]]) for one in seen], axis=1
        )
        runs = np.repeat(np.arange(4), count)
        total = _log_likelihood(
            state,
            covariance,
            probability,
            np.tile(np.arange(count), 4),
            encounter.steps,
            xy[:, runs],
            view_covariance[:, runs],
            sigma,
            self._sojourn,
        ).reshape(4, count)
        return float(np.max(total[2] + total[3] - total[0] - total[1]))

    def _open_new(
        self, tracks: TrackTable, ids: np.ndarray, people: np.ndarray, timestamp: float
    ) -> None:
        """Open an encounter for each pair of people closer than ``swap_radius_m`` that has
        none, under the ids the tracks carry after this instant's swaps (``ids``)."""
        rows = np.flatnonzero(people)
        if len(rows) < 2:
            return
        xy = tracks.state[rows, :2]
        first, second = close_pairs(xy, xy, np.full(len(rows), self.context.config.swap_radius_m))
        keep = first < second
        for a, b in zip(rows[first[keep]].tolist(), rows[second[keep]].tolist(), strict=True):
            one, other = int(ids[a]), int(ids[b])
            key = (min(one, other), max(one, other))
            if key in self._open:
                continue
            self._open[key] = _Encounter(
                opened=timestamp,
                last=timestamp,
                states={one: [], other: []},
                views={one: [], other: []},
                serial=self._serial,
            )
            self._serial += 1

    def _rename(self, swaps: list[tuple[int, int]], tracks: TrackTable) -> None:
        """After the tracker exchanges ids, what each open encounter recorded under an id
        belongs to the track that carries the other id now."""
        other: dict[int, int] = {}
        for a, b in swaps:
            one, two = int(tracks.ids[a]), int(tracks.ids[b])
            other[one], other[two] = two, one
        renamed: dict[tuple[int, int], _Encounter] = {}
        for (first, second), encounter in self._open.items():
            first_new, second_new = other.get(first, first), other.get(second, second)
            encounter.states = {other.get(k, k): v for k, v in encounter.states.items()}
            encounter.views = {other.get(k, k): v for k, v in encounter.views.items()}
            renamed[(min(first_new, second_new), max(first_new, second_new))] = encounter
        self._open = renamed
        runs = self._runs
        runs.owner, runs.seen = (
            np.array([other.get(one, one) for one in ids.tolist()], np.int64)
            for ids in (runs.owner, runs.seen)
        )

    def get_state(self) -> list[dict]:
        """The open encounters as JSON-ready data, restored by :meth:`set_state`."""
        return [
            {
                "ids": list(key),
                "opened": encounter.opened,
                "last": encounter.last,
                "apart_since": encounter.apart_since,
                "steps": list(encounter.steps),
                "states": {
                    str(k): [[part.tolist() for part in one] for one in v]
                    for k, v in encounter.states.items()
                },
                "views": {
                    str(k): [[part.tolist() for part in one] for one in v]
                    for k, v in encounter.views.items()
                },
            }
            for key, encounter in self._open.items()
        ]

    def set_state(self, state: list[dict] | None) -> None:
        """Restore :meth:`get_state`'s data (None: no open encounter)."""
        self.reset()
        for item in state or []:
            key = (int(item["ids"][0]), int(item["ids"][1]))
            self._open[key] = _Encounter(
                opened=float(item["opened"]),
                last=float(item["last"]),
                apart_since=None if item["apart_since"] is None else float(item["apart_since"]),
                steps=[float(step) for step in item["steps"]],
                states={
                    int(k): [tuple(np.asarray(part, np.float64) for part in one) for one in v]
                    for k, v in item["states"].items()
                },
                views={
                    int(k): [tuple(np.asarray(part, np.float64) for part in one) for one in v]
                    for k, v in item["views"].items()
                },
            )


_UNSEEN = (np.full(2, np.nan), np.eye(2))
_SIDES = np.array([0, 1])  # an encounter's two tracks' rows in the recorded states
_FEW_SERIALS = 16  # encounters dropped at once, up to which a comparison table is cheaper


@dataclass
class _Runs:
    """The filters of every open encounter, one row each: run from one instant's state of
    track ``owner`` through the views of track ``seen``; ``total``, their log-likelihood."""

    state: np.ndarray  # (R, M, 4)
    covariance: np.ndarray  # (R, M, 4, 4)
    probability: np.ndarray  # (R, M)
    acceleration: np.ndarray  # (R, M)
    serial: np.ndarray  # (R,) its encounter's
    owner: np.ndarray  # (R,) id
    seen: np.ndarray  # (R,) id
    total: np.ndarray  # (R,)
    keep: np.ndarray  # (R,) log-likelihood of the run of its start through its own views

    @classmethod
    def empty(cls, models: int) -> _Runs:
        nothing = np.zeros(0, np.int64)
        return cls(
            np.zeros((0, models, 4)),
            np.zeros((0, models, 4, 4)),
            np.zeros((0, models)),
            np.zeros((0, models)),
            nothing,
            nothing,
            nothing,
            np.zeros(0),
            np.zeros(0),
        )

    def append(self, state, covariance, probability, acceleration, serial, owner, seen):
        """New runs, their log-likelihood 0."""
        self.state = np.concatenate([self.state, state])
        self.covariance = np.concatenate([self.covariance, covariance])
        self.probability = np.concatenate([self.probability, probability])
        self.acceleration = np.concatenate([self.acceleration, acceleration])
        self.serial = np.concatenate([self.serial, serial])
        self.owner = np.concatenate([self.owner, owner])
        self.seen = np.concatenate([self.seen, seen])
        self.total = np.concatenate([self.total, np.zeros(len(state))])
        self.keep = np.concatenate([self.keep, np.zeros(len(state))])

    def drop(self, serials: set[int]) -> None:
        """Forget the runs of these encounters."""
        if not len(self.serial) or not serials:
            return
        if len(serials) <= _FEW_SERIALS:
            # (a few serials against a few hundred runs: one comparison table costs less
            # than np.isin's sorting; the same mask)
            wanted = np.fromiter(serials, np.int64, len(serials))
            kept = ~(self.serial[:, None] == wanted).any(axis=1)
        else:
            kept = ~np.isin(self.serial, list(serials))
        if kept.all():
            return
        for one in fields(self):
            setattr(self, one.name, getattr(self, one.name)[kept])


def _log_likelihood(
    state: np.ndarray,
    covariance: np.ndarray,
    probability: np.ndarray,
    starts: np.ndarray,
    steps: list[float],
    xy: np.ndarray,
    view_covariance: np.ndarray,
    sigma: np.ndarray,
    sojourn: np.ndarray,
) -> np.ndarray:
    """(B,) log-likelihood of the views under the motion models, for B filters (``state``
    (B, M, 4) and so on), filter ``b`` started at step ``starts[b]`` and fed ``xy[s, b]``
    ((S, B, 2), NaN: unseen) with covariance ``view_covariance[s, b]`` at each step s."""
    total = np.zeros(len(state))
    acceleration = np.repeat(sigma[None], len(state), axis=0)
    for index, step in enumerate(steps):
        active = np.flatnonzero(starts <= index)
        mode_state, mode_covariance, mode_probability, seen, gain = _step(
            state[active],
            covariance[active],
            probability[active],
            step,
            xy[index, active],
            view_covariance[index, active],
            acceleration[active],
            sojourn,
        )
        total[active[seen]] += gain
        state[active], covariance[active] = mode_state, mode_covariance
        probability[active] = mode_probability
    return total


def _step(
    state: np.ndarray,
    covariance: np.ndarray,
    probability: np.ndarray,
    step: float,
    xy: np.ndarray,
    view_covariance: np.ndarray,
    acceleration: np.ndarray,
    sojourn: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step of B filters (``state`` (B, M, 4) and so on) fed ``xy`` (B, 2) (NaN: unseen):
    their new states, which saw a view, and the log-likelihood of each of those views."""
    mode_state, mode_covariance, mode_probability = kalman.predict_models(
        state, covariance, probability, step, acceleration, sojourn
    )
    seen = ~np.isnan(xy[:, 0])
    gain = np.zeros(0)
    if seen.any():
        # The update's own innovations give each model's likelihood of the view (closed-form
        # 2 x 2 inverses, as the tracker's filter uses them).
        prior = mode_probability[seen]
        (mode_state[seen], mode_covariance[seen], mode_probability[seen],
         likelihood) = kalman.update_models_likelihood(
            mode_state[seen], mode_covariance[seen], prior, xy[seen], view_covariance[seen])
        log = likelihood + np.log(np.maximum(prior, 1e-300))
        peak = log.max(axis=1)
        gain = peak + np.log(np.exp(log - peak[:, None]).sum(axis=1))
    return mode_state, mode_covariance, mode_probability, seen, gain
