"""Camera clock offsets, estimated from the data: a camera whose clock is off sees the past.

A camera whose clock is ``d`` seconds ahead stamps what it saw at true time ``t`` with
``t + d``; fused at that time, each of its locations trails the object by about ``v * d``
(``v`` the object's velocity). Two estimators recover ``d`` from nothing but the located
detections and the tracks:

* **fine** (milliseconds to a few hundred milliseconds): each view, moved to its window's
  time along its track's velocity, is compared across its camera's ray with the fusion of
  the same track's other views in the window (or with the track's prediction when it is
  alone): the residual is about ``-v * (d_camera - d_others)`` plus noise and a bias. The
  bias can follow the flow of people (in a street everyone walks one way; a calibration or a
  foot point a few centimetres off then looks exactly like a clock error), so the fit is
  made *within* ground cells of ``cell_m``: a bias per camera and cell, one offset per camera,
  what is left is what varies with the velocity in one place. On WILDTRACK a pooled fit finds
  "offsets" of 50-130 ms on synchronised cameras; the within-cell fit does not. Evidence is
  queued and learnt in a batch every ``solve_every_s``, forgotten over ``memory_s``; each
  camera's estimate is measured against the others, so of C cameras' estimates ``(C - 1) /
  C`` is applied, damped while it rests on little data. Nothing moves until some camera's
  estimate is beyond ``significance`` standard errors (synchronised cameras keep their
  timestamps exactly); then every camera follows its estimate. Only relative offsets are
  observable (all clocks shifted alike change nothing): offsets are kept relative to the
  median camera.
* **coarse** (seconds: a wrong clock): every ``search_every_s`` a camera whose locations
  rarely land on tracks other cameras see (its corroboration below half the median
  camera's), and every ``turn_every_s`` the next camera in turn, is compared with the recent
  history of the other cameras' tracks at every lag within ``max_offset_s``: the lag at which
  clearly more of its locations sit on those tracks than at its current offset becomes its
  offset. The fine estimator then refines it.

A camera whose offset exceeds ``tolerance_s`` is reported (an event, logged by the tracker,
and in :meth:`ClockModel.report`); all offsets are corrected whatever their size.

It stays one module because the two estimators share one state (the queued views, the
history of tracks, the offsets they both move) that :class:`ClockModel` saves and restores as
one piece; splitting it would pass that state between modules.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.arrays import median_of_few, unique_integers
from cblrs.matching.neighbours import chebyshev_pairs

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

DEFAULT_TOLERANCE_S = 0.2
"""Clock offsets beyond this are reported (all are corrected)."""
DEFAULT_MAX_OFFSET_S = 5.0
"""Largest clock error the coarse search looks for, seconds."""
_CELL_OFFSET = 1 << 20  # ground cells are packed as 21-bit non-negative numbers
_FIVE = np.arange(5)  # the columns of the per-cell sums


@dataclass(frozen=True)
class ClockEvent:
    """Something worth telling an operator about a camera's clock.

    Attributes:
        camera: the camera's index.
        kind: ``"off"`` (its offset went beyond the tolerance), ``"jump"`` (the coarse search
            moved its offset) or ``"back"`` (its offset returned within the tolerance).
        offset_s: the camera's estimated offset afterwards, seconds (positive: ahead).
        time_s: the tracker's time then, seconds.
    """

    camera: int
    kind: str
    offset_s: float
    time_s: float


class ClockModel:
    """Per-camera clock offsets (corrected capture time = camera timestamp - offset).

    Args:
        camera_count: number of cameras C.
        tolerance_s: offsets beyond this are reported.
        max_offset_s: search range of the coarse estimator, seconds (0 turns it off).
        estimate: False keeps every offset at 0 (no estimation at all).
    """

    memory_s = 20.0
    """Evidence of the fine estimator older than this many seconds counts ``1/e`` as much."""
    prior_information = 2500.0
    """Damping of each fine step, in the units of the information (1/s^2): a 20 ms prior."""
    minimum_information = 200.0
    """Fine evidence a camera needs before its offset moves at all (1/s^2)."""
    corroboration_memory_s = 5.0
    search_every_s = 2.0
    """How often a camera whose locations stopped landing on the others' tracks is searched."""
    turn_every_s = 6.0
    """How often the next camera in turn is searched when none stands out."""
    settled_information = 1.0 / 0.004**2
    """Evidence (1/s^2) beyond which a camera's offset is known to 4 ms: learn less often."""
    views = 48
    settled_views = 12
    hit_radius_m = 0.5
    minimum_excess = 0.1
    history_step_s = 0.1
    solve_every_s = 0.5
    """Fraction of a camera's detections more that must fit the tracks at a new lag."""
    sample_limit = 200
    kept_events = 100
    apply_corrections = True
    significance = 3.0
    """A step of the fine estimate is applied when beyond this many standard errors."""
    cell_m = 2.0
    cell_bias_sigma_m = 0.1

    def __init__(
        self,
        camera_count: int,
        tolerance_s: float = DEFAULT_TOLERANCE_S,
        max_offset_s: float = DEFAULT_MAX_OFFSET_S,
        estimate: bool = True,
    ):
        self.camera_count = int(camera_count)
        self.tolerance_s = float(tolerance_s)
        self.max_offset_s = float(max_offset_s)
        self.estimate = bool(estimate)
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        count = self.camera_count
        self.offsets = np.zeros(count)
        # Within-cell sums per (camera, ground cell), sorted by their packed key.
        self._keys = np.zeros(0, np.int64)
        self._key_camera = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 5))
        self._gain = 1.0
        self._fit = (np.zeros(count), np.zeros(count))  # information, score at the last solve
        self._next_solve: float | None = None
        self._time: float | None = None
        self._located = np.zeros(count)
        self._corroborated = np.zeros(count)
        self._flagged = np.zeros(count, dtype=bool)
        self._active = np.zeros(count, dtype=bool)  # cameras whose offset has been moved
        self._next_search: float | None = None
        self._next_turn: float | None = None
        self._turn = -1
        self._queued: list[tuple[np.ndarray, ...]] = []  # views waiting for the next solve
        self._queued_groups = 0
        self._stale = np.zeros(count, np.int64)
        self._jumps = np.zeros(count, np.int64)
        # Coarse search material: confirmed tracks per window (time, positions, the only
        # camera that saw each or -1) and per camera its recent located detections.
        self._history: deque[tuple[float, FloatArray, IntArray]] = deque()
        self._samples: list[deque[tuple[float, FloatArray]]] = [deque() for _ in range(count)]
        self._events: list[ClockEvent] = []

    # ----------------------------------------------------------------------- evidence
    def add_views(
        self,
        camera: IntArray,
        track: IntArray,
        world_xy: FloatArray,
        covariance: FloatArray,
        velocity: FloatArray,
        across: FloatArray | None,
        predicted_xy: FloatArray,
        predicted_covariance: FloatArray,
    ) -> None:
        """Queue one window's views (the arguments of :meth:`learn`); they are learnt in one
        batch before the offsets are next solved (a few numpy calls per batch rather than per
        window)."""
        if not self.estimate or len(camera) == 0:
            return
        if across is None:
            across = np.zeros((len(camera), 2))  # no ray known: both axes
        self._queued.append((camera, track + self._queued_groups, world_xy, covariance,
                             velocity, across, predicted_xy, predicted_covariance))
        self._queued_groups += int(track.max()) + 1

    def _learn_queued(self) -> None:
        if not self._queued:
            return
        # (One window queued, as when every window is solved: its arrays as they are.)
        parts = [column[0] if len(column) == 1 else np.concatenate(column)
                 for column in zip(*self._queued, strict=True)]
        self._queued, self._queued_groups = [], 0
        camera, track, world_xy, covariance, velocity, across, predicted, spread = parts
        known = np.any(across != 0, axis=1)
        if known.all():  # (every camera placed: all views at once, without selecting them)
            _, label = np.unique(track, return_inverse=True)
            self.learn(camera, label.reshape(-1), world_xy, covariance, velocity, across,
                       predicted, spread)
            return
        for mask, normals in ((known, across), (~known, None)):
            if mask.any():
                _, label = np.unique(track[mask], return_inverse=True)
                self.learn(camera[mask], label.reshape(-1), world_xy[mask], covariance[mask],
                           velocity[mask], None if normals is None else normals[mask],
                           predicted[mask], spread[mask])

    def learn(
        self,
        camera: IntArray,
        track: IntArray,
        world_xy: FloatArray,
        covariance: FloatArray,
        velocity: FloatArray,
        across: FloatArray | None = None,
        predicted_xy: FloatArray | None = None,
        predicted_covariance: FloatArray | None = None,
    ) -> None:
        """Add fine evidence: views of tracks that other cameras see too.

        Each view, moved to the window's time with its track's velocity ``v``, is compared
        with the fusion of the track's other views in the window, or, when it is the only
        one (cameras whose clocks are off by more than the window capture apart), with its
        track's prediction (from the other cameras' recent views as much as its own): if its
        camera's clock is ``d`` ahead of theirs, it sits about ``-v d`` off. Only the
        component across the camera's viewing ray is used: along the ray a walking person's
        foot point moves with the gait (the box bottom is the nearer foot), an error that
        grows with speed just as a clock error does, while across the ray a box locates the
        body's centre line.

        Args:
            camera: (N,) camera index of each view.
            track: (N,) its track.
            world_xy: (N, 2) its position, moved to the window's time, metres.
            covariance: (N, 2, 2) its measurement covariance, square metres.
            velocity: (N, 2) its track's velocity, m/s.
            across: (N, 2) unit vectors across each view's ray; None uses both axes.
            predicted_xy: (N, 2) its track's prediction at the window's time, metres; views
                alone in the window are compared with it (None: they are left out).
            predicted_covariance: (N, 2, 2) the prediction's covariance, square metres.
        """
        if not self.estimate or len(camera) == 0:
            return
        information, _ = _inverse_2x2(covariance)
        weighted = np.einsum("nij,nj->ni", information, world_xy)
        # Sums over each track's views (bincount: far faster than np.add.at).
        groups = int(track.max()) + 1
        # The five sums in one bincount, each adding its terms in view order as five would.
        terms = np.column_stack([information[:, 0, 0], information[:, 0, 1],
                                 information[:, 1, 1], weighted])  # (N, 5)
        keys = (np.asarray(track, np.int64)[:, None] * 5 + np.arange(5)).reshape(-1)
        sums = np.bincount(keys, terms.reshape(-1), 5 * groups).reshape(groups, 5)
        total, vector = sums[:, :3], sums[:, 3:]
        label = track
        others = np.empty_like(information)  # the information of the other views
        others[:, 0, 0] = total[track, 0] - information[:, 0, 0]
        others[:, 0, 1] = others[:, 1, 0] = total[track, 1] - information[:, 0, 1]
        others[:, 1, 1] = total[track, 2] - information[:, 1, 1]
        alone = np.abs(others[:, 0, 0] * others[:, 1, 1] - others[:, 0, 1] ** 2) < 1e-12
        if predicted_xy is None or predicted_covariance is None:
            views = np.flatnonzero(~alone)
        else:
            views = np.arange(len(camera))
        if len(views) == 0:
            return
        reference = np.zeros((len(views), 2))
        other_covariance = np.zeros((len(views), 2, 2))
        paired = ~alone[views]
        if paired.any():
            other_covariance[paired], _ = _inverse_2x2(others[views[paired]])
            reference[paired] = np.einsum(
                "nij,nj->ni", other_covariance[paired],
                vector[label[views[paired]]] - weighted[views[paired]])
        if not paired.all():
            single = views[~paired]
            reference[~paired] = predicted_xy[single]  # type: ignore[index]
            other_covariance[~paired] = predicted_covariance[single]  # type: ignore[index]
        residual = world_xy[views] - reference
        spread = covariance[views] + other_covariance
        if across is None:
            directions = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
            projections = [np.broadcast_to(direction, (len(views), 2))
                           for direction in directions]
        else:
            projections = [across[views]]
        for axis, normal in enumerate(projections):
            # residual_n = x (d_camera - d_others) + b: x = -v along the normal, and b the
            # camera's bias where the view lies, along this normal (see :meth:`_accumulate`).
            residual_n = np.sum(normal * residual, axis=1)
            variance = np.einsum("ni,nij,nj->n", normal, spread, normal)
            slope = -np.sum(normal * velocity[views], axis=1)
            self._accumulate(camera[views], world_xy[views], slope, residual_n, 1.0 / variance,
                             axis)

    def _accumulate(
        self, camera: IntArray, world_xy: FloatArray, slope: FloatArray, value: FloatArray,
        weight: FloatArray, axis: int = 0,
    ) -> None:
        """Weighted sums per camera and ground cell of ``value = slope * offset + bias``.

        A camera's views can be biased by where they lie (a foot point off by the body's
        radius towards the camera, a calibration error), and where people keep walking in
        one direction such a bias grows with their velocity exactly as a clock error does.
        Fitting the offset within each cell (a bias per cell and camera, the offset shared)
        leaves only what varies with the velocity in one place: a clock.
        """
        cells = np.floor(world_xy / self.cell_m).astype(np.int64) + _CELL_OFFSET
        keys = ((camera.astype(np.int64) << 43) | (axis << 42) | (cells[:, 0] << 21)
                | cells[:, 1])
        index = np.searchsorted(self._keys, keys)
        known = index < len(self._keys)
        known[known] = self._keys[index[known]] == keys[known]
        if not known.all():
            new = unique_integers(keys[~known])
            self._keys = np.concatenate([self._keys, new])
            self._key_camera = np.concatenate([self._key_camera, new >> 43])
            self._sums = np.concatenate([self._sums, np.zeros((len(new), 5))])
            order = np.argsort(self._keys, kind="stable")
            self._keys, self._key_camera = self._keys[order], self._key_camera[order]
            self._sums = self._sums[order]
            index = np.searchsorted(self._keys, keys)
        # Stored sums are the true ones divided by the running decay (see end_window).
        weight = weight / self._gain
        rows = len(self._sums)
        # The five sums in one bincount, each adding its terms in view order as five would.
        parts = np.empty((len(index), 5))
        parts[:, 0] = weight
        parts[:, 1] = weight * slope
        parts[:, 2] = weight * value
        parts[:, 3] = weight * slope * slope
        parts[:, 4] = weight * slope * value
        keys = (index[:, None] * 5 + _FIVE).reshape(-1)
        self._sums += np.bincount(keys, parts.reshape(-1), 5 * rows).reshape(rows, 5)

    def _within(self) -> tuple[FloatArray, FloatArray]:
        """(C,) information and (C,) score of the within-cell fit: offset = score / information."""
        sums = self._sums * self._gain
        camera = self._key_camera
        # The bias of a cell has a prior (``cell_bias_sigma_m``): a cell seen a few times
        # adds what the pooled fit would; one seen often, only its variation in velocity.
        total = sums[:, 0] + 1.0 / self.cell_bias_sigma_m**2
        information = sums[:, 3] - sums[:, 1] ** 2 / total
        score = sums[:, 4] - sums[:, 1] * sums[:, 2] / total
        count = self.camera_count
        return (np.bincount(camera, information, count).astype(np.float64),
                np.bincount(camera, score, count).astype(np.float64))

    def corroboration(self, camera: IntArray, corroborated: BoolArray) -> None:
        """Count located detections per camera and those on tracks other cameras see."""
        self._located += np.bincount(camera, minlength=self.camera_count)
        self._corroborated += np.bincount(camera, corroborated.astype(np.float64),
                                          self.camera_count)

    def record(
        self, time_s: float, positions: FloatArray, sole_camera: IntArray,
        camera: IntArray, world_xy: FloatArray, raw_time: FloatArray,
    ) -> None:
        """Keep material for the coarse search.

        Args:
            time_s: the window's time (the tracker's timeline), seconds.
            positions: (K, 2) confirmed tracks seen in the window, metres.
            sole_camera: (K,) the only camera that saw each of them recently, -1 if several.
            camera: (N,) camera of each located detection of the window.
            world_xy: (N, 2) their positions, metres.
            raw_time: (N,) their cameras' own timestamps, seconds.
        """
        if not self.estimate or self.max_offset_s <= 0:
            return
        if not self._history or time_s - self._history[-1][0] >= self.history_step_s:
            self._history.append((float(time_s), positions.copy(), sole_camera.copy()))
        horizon = float(time_s) - 2.5 * self.max_offset_s - self.search_every_s
        while self._history and self._history[0][0] < horizon:
            self._history.popleft()
        cameras, first = np.unique(camera, return_index=True)  # each one's first detection
        for one, stamp in zip(cameras.tolist(), raw_time[first].tolist(), strict=True):
            samples = self._samples[one]
            if samples and stamp - samples[-1][0] < self.history_step_s:
                continue
            samples.append((stamp, world_xy[camera == one].copy()))
            while samples and samples[0][0] - self.offsets[one] < horizon:
                samples.popleft()

    def stale(self, camera: int) -> None:
        """Count a message that came too late to be fused."""
        self._stale[camera] += 1

    # ---------------------------------------------------------------------- decisions
    def end_window(self, time_s: float) -> list[ClockEvent]:
        """Apply the evidence of a window ending at ``time_s`` (tracker time, seconds).

        Returns:
            The events this produced (also kept for :meth:`events`).
        """
        if not self.estimate:
            return []
        before = len(self._events)
        if self._time is not None and time_s > self._time:
            self._gain *= math.exp(-(time_s - self._time) / self.memory_s)
            if self._gain < 1e-100:
                self._sums *= self._gain
                self._gain = 1.0
            corroboration_decay = math.exp(
                -(time_s - self._time) / self.corroboration_memory_s)
            self._located *= corroboration_decay
            self._corroborated *= corroboration_decay
        self._time = time_s if self._time is None else max(self._time, time_s)
        if self._next_solve is None or self._time >= self._next_solve:
            self._next_solve = self._time + self.solve_every_s
            self._learn_queued()
            self._fit = self._within()
            step = self.solve()
            if self.apply_corrections and step is not None:
                self._active |= step != 0
                self.offsets += step
                # The evidence so far is about the offsets before this step: re-base it
                # (value -= slope * step, per cell).
                shift = step[self._key_camera]
                self._sums[:, 2] -= shift * self._sums[:, 1]
                self._sums[:, 4] -= shift * self._sums[:, 3]
                self._fit = self._within()
            self._centre()
        self._search(self._time)
        self._report(self._time)
        new = self._events[before:]
        if len(self._events) > self.kept_events:
            del self._events[: len(self._events) - self.kept_events]
        return new

    @property
    def _information(self) -> FloatArray:
        return self._fit[0]

    def solve(self) -> FloatArray | None:
        """(C,) the offset corrections the evidence asks for (None: too little evidence)."""
        information, score = self._fit
        ready = information >= self.minimum_information
        if ready.sum() < 2:
            return None
        estimate = np.where(ready, score / (information + self.prior_information), 0.0)
        # Each camera is measured against the others, whose offsets are corrected in the
        # same step: of C cameras' estimates d_c - mean(others), (C - 1) / C of each moves
        # every camera to d_c - mean(all) (all of it would overshoot; two cameras would swap).
        count = int(ready.sum())
        step = estimate * (count - 1) / count
        # The first correction needs a significant estimate: on synchronised cameras it
        # wanders within its noise and must not move their timestamps. Once one camera has
        # been shown off, every camera's offset follows its estimate.
        with np.errstate(divide="ignore"):
            significant = np.abs(estimate) > self.significance / np.sqrt(information)
        if not self._active.any() and not significant.any():
            return np.zeros(self.camera_count)
        return np.where(ready, step, 0.0)

    def _centre(self) -> None:
        """Keep offsets relative to the median camera (a common shift is unobservable)."""
        informed = self._information >= self.minimum_information
        if informed.sum() >= 2:
            self.offsets -= median_of_few(self.offsets[informed])

    def _report(self, time_s: float) -> None:
        if not self._flagged.any() and float(np.abs(self.offsets).max(initial=0.0)) <= (
                self.tolerance_s):
            return  # no camera off, none was: nothing to report or change
        off = np.abs(self.offsets) > self.tolerance_s
        back = np.abs(self.offsets) <= 0.5 * self.tolerance_s
        for camera in np.flatnonzero(off & ~self._flagged).tolist():
            self._events.append(ClockEvent(camera, "off", float(self.offsets[camera]), time_s))
        for camera in np.flatnonzero(back & self._flagged).tolist():
            self._events.append(ClockEvent(camera, "back", float(self.offsets[camera]), time_s))
        self._flagged = (self._flagged | off) & ~back

    def _suspect(self) -> int | None:
        """The least corroborated camera, if it falls below half the median camera's."""
        enough = self._located >= 20
        if enough.sum() >= 2:
            ratio = np.where(enough, self._corroborated / np.maximum(self._located, 1e-9),
                             np.nan)
            typical = median_of_few(ratio[enough])  # np.nanmedian's value, without numpy.ma
            worst = int(np.nanargmin(ratio))
            if typical >= 0.3 and ratio[worst] < 0.5 * typical:
                return worst
        return None

    @property
    def view_budget(self) -> int:
        """About how many views per window to learn from: fewer once every camera's offset
        is known to a few milliseconds (the evidence then only follows a drifting clock;
        learning costs time). Every window contributes, so no capture pattern is favoured."""
        if (self._fit[0] >= self.settled_information).all():
            return self.settled_views
        return self.views

    def _search(self, time_s: float) -> None:
        """Every ``search_every_s`` of stream, look for one camera's clock at every lag."""
        if self.max_offset_s <= 0 or len(self._history) < 3:
            return
        if self._next_search is not None and time_s < self._next_search:
            return
        self._next_search = time_s + self.search_every_s
        camera = self._suspect()
        if camera is None:
            # No camera stands out: look at each in turn, less often.
            if self._next_turn is not None and time_s < self._next_turn:
                return
            self._next_turn = time_s + self.turn_every_s
            self._turn = (self._turn + 1) % self.camera_count
            camera = self._turn
        found = self._best_lag(camera)
        if found is None:
            return
        lag, gain = found
        if abs(lag - self.offsets[camera]) <= self.tolerance_s or gain < 2.0:
            return
        self.offsets[camera] = lag
        self._active[camera] = True
        self._flagged[camera] = abs(lag) > self.tolerance_s  # reported by the jump itself
        self._sums[self._key_camera == camera] = 0.0
        self._located[camera] = self._corroborated[camera] = 0.0
        self._jumps[camera] += 1
        self._events.append(ClockEvent(camera, "jump", float(lag), time_s))

    def _best_lag(self, camera: int) -> tuple[float, float] | None:
        """The lag at which the camera's detections best fit other cameras' tracks.

        Every recent detection of the camera is compared with the recent history of the
        tracks other cameras see, at every lag within ``max_offset_s``: the rate at which it
        lies within ``hit_radius_m`` of a track, per 0.1 s of lag. Standing people fit at
        every lag; walking ones only at the camera's offset.

        Returns:
            ``(lag, gain)``: the lag (seconds, the offset it implies) and how many times more
            of the camera's detections fit a track there than at its current offset; None
            when there is too little to decide.
        """
        samples = list(self._samples[camera])
        if len(samples) < 5:
            return None
        times = np.concatenate([np.full(len(xy), t) for t, xy in samples])
        points = np.concatenate([xy for _, xy in samples])
        if len(points) > self.sample_limit:
            keep = np.linspace(0, len(points) - 1, self.sample_limit).astype(np.int64)
            times, points = times[keep], points[keep]
        if len(points) < 20:
            return None
        entry_times: list[float] = []
        history_points: list[FloatArray] = []
        history_times: list[FloatArray] = []
        history_entry: list[IntArray] = []
        for history_time, positions, sole in self._history:
            others = positions[sole != camera]
            if len(others):
                history_entry.append(np.full(len(others), len(entry_times)))
                entry_times.append(history_time)
                history_points.append(others)
                history_times.append(np.full(len(others), history_time))
        if len(entry_times) < 3:
            return None
        entry_time = np.asarray(entry_times)
        origin = float(entry_time[-1])
        bin_s = 0.1
        bins = round(self.max_offset_s / bin_s)
        # Every (detection, history instant) pair within the lag range ...
        lags = (times - origin)[:, None] - (entry_time - origin)[None, :]
        within = np.abs(lags) <= self.max_offset_s
        pairs = np.bincount(np.rint(lags[within] / bin_s).astype(np.int64) + bins,
                            minlength=2 * bins + 1).astype(np.float64)
        # ... and those where another camera's track was near the detection: one query in
        # space and time (Chebyshev distance, time scaled so the lag range spans the radius).
        scale = self.hit_radius_m / self.max_offset_s
        sample, near = chebyshev_pairs(
            np.column_stack([points, (times - origin) * scale]),
            np.column_stack([np.concatenate(history_points),
                             (np.concatenate(history_times) - origin) * scale]),
            self.hit_radius_m,
        )
        hits = np.zeros(2 * bins + 1)
        if len(sample):
            entry = np.concatenate(history_entry)[near]
            # One hit per (detection, instant), however many tracks were near.
            pair = unique_integers(sample * len(entry_time) + entry)
            sample, entry = pair // len(entry_time), pair % len(entry_time)
            lag = (times[sample] - origin) - (entry_time[entry] - origin)
            np.add.at(hits, np.rint(lag / bin_s).astype(np.int64) + bins, 1.0)
        counted = pairs >= max(10.0, 0.2 * pairs.max())
        if counted.sum() < 3:
            return None
        rate = np.where(counted, hits / np.maximum(pairs, 1.0), np.nan)
        # Standing people fit at every lag: measure each lag's fit above that baseline.
        excess = rate - median_of_few(rate[counted])  # np.nanmedian's value, without numpy.ma
        excess = np.where(counted, excess, -np.inf)
        best = int(np.argmax(excess))
        current = int(np.clip(round(self.offsets[camera] / bin_s) + bins, 0, 2 * bins))
        # Neighbouring bins share the true lag's hits: compare against the best around the
        # current offset.
        around = float(excess[max(0, current - 1):current + 2].max())
        if excess[best] < self.minimum_excess:
            return None
        # Slow walkers fit over a range of lags around the true one: take the middle of the
        # run of lags that fit nearly as well as the best (excess-weighted).
        threshold = 0.9 * excess[best]
        low = high = best
        while low > 0 and excess[low - 1] >= threshold:
            low -= 1
        while high < 2 * bins and excess[high + 1] >= threshold:
            high += 1
        window = np.arange(low, high + 1)
        weights = excess[window]
        estimate = float(np.sum((window - bins) * bin_s * weights) / np.sum(weights))
        return estimate, float(excess[best] / max(around, 0.01))

    # ------------------------------------------------------------------------ reports
    def events(self) -> list[ClockEvent]:
        """Events since the last call (and forget them)."""
        events, self._events = self._events, []
        return events

    @property
    def uncertainty_s(self) -> FloatArray:
        """(C,) standard error of each fine offset estimate, seconds (inf without evidence)."""
        with np.errstate(divide="ignore"):
            return 1.0 / np.sqrt(self._information)

    def report(self, camera_ids: Sequence[str]) -> dict[str, dict[str, Any]]:
        """Per camera: offset, its uncertainty, whether reported, corroboration, counts."""
        uncertainty = self.uncertainty_s
        corroboration = np.where(
            self._located > 0, self._corroborated / np.maximum(self._located, 1e-9), np.nan)
        return {
            name: {
                "offset_s": float(self.offsets[index]),
                "uncertainty_s": None if not np.isfinite(uncertainty[index])
                else float(uncertainty[index]),
                "beyond_tolerance": bool(self._flagged[index]),
                "corroboration": None if not np.isfinite(corroboration[index])
                else float(corroboration[index]),
                "coarse_corrections": int(self._jumps[index]),
                "stale_messages": int(self._stale[index]),
            }
            for index, name in enumerate(camera_ids)
        }

    # -------------------------------------------------------------------------- state
    def get_state(self) -> dict[str, Any]:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "offsets": self.offsets.tolist(),
            "keys": self._keys.tolist(),
            "sums": (self._sums * self._gain).tolist(),
            "next_solve": self._next_solve,
            "fit": [self._fit[0].tolist(), self._fit[1].tolist()],
            "time": self._time,
            "located": self._located.tolist(),
            "corroborated": self._corroborated.tolist(),
            "flagged": self._flagged.tolist(),
            "active": self._active.tolist(),
            "next_search": self._next_search,
            "next_turn": self._next_turn,
            "turn": self._turn,
            "queued": [[column.tolist() for column in views] for views in self._queued],
            "queued_groups": self._queued_groups,
            "stale": self._stale.tolist(),
            "jumps": self._jumps.tolist(),
            "history": [[t, positions.tolist(), sole.tolist()]
                        for t, positions, sole in self._history],
            "samples": [[[t, xy.tolist()] for t, xy in samples] for samples in self._samples],
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore a state saved by :meth:`get_state`."""
        self.reset()
        self.offsets = np.asarray(state["offsets"], np.float64).reshape(self.camera_count)
        self._keys = np.asarray(state["keys"], np.int64).reshape(-1)
        self._key_camera = self._keys >> 43
        self._sums = np.asarray(state["sums"], np.float64).reshape(-1, 5)
        self._next_solve = state["next_solve"]
        self._fit = (np.asarray(state["fit"][0], np.float64),
                     np.asarray(state["fit"][1], np.float64))
        self._time = None if state["time"] is None else float(state["time"])
        self._located = np.asarray(state["located"], np.float64).reshape(-1)
        self._corroborated = np.asarray(state["corroborated"], np.float64).reshape(-1)
        self._flagged = np.asarray(state["flagged"], bool).reshape(-1)
        self._active = np.asarray(state["active"], bool).reshape(-1)
        self._next_search = state["next_search"]
        self._next_turn = state["next_turn"]
        self._turn = int(state["turn"])
        self._queued = [
            tuple(np.asarray(column, np.int64 if index < 2 else np.float64)
                  for index, column in enumerate(views))
            for views in state["queued"]
        ]
        self._queued_groups = int(state["queued_groups"])
        self._stale = np.asarray(state["stale"], np.int64).reshape(-1)
        self._jumps = np.asarray(state["jumps"], np.int64).reshape(-1)
        self._history = deque(
            (float(t), np.asarray(p, np.float64).reshape(-1, 2), np.asarray(s, np.int64))
            for t, p, s in state["history"]
        )
        self._samples = [
            deque((float(t), np.asarray(xy, np.float64).reshape(-1, 2)) for t, xy in samples)
            for samples in state["samples"]
        ]


def _inverse_2x2(matrices: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(K, 2, 2) inverses and (K,) determinants of (K, 2, 2) matrices (closed form)."""
    a, b, c, d = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 0], matrices[:, 1, 1]
    determinant = a * d - b * c
    inverse = np.empty_like(matrices)
    inverse[:, 0, 0] = d / determinant
    inverse[:, 0, 1] = -b / determinant
    inverse[:, 1, 0] = -c / determinant
    inverse[:, 1, 1] = a / determinant
    return inverse, determinant
