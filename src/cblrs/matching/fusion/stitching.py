"""Repair after assignment (step 7 of the fusion tracker's update): a new track that continues a
lost one takes its id.

An object nobody sees for a while (hidden in a crowd, behind a bus, missed by the detector)
leaves its track coasting; when it is seen again its track may not take it back (it walked off
its prediction, a neighbour's view was nearer), the track is dropped after ``max_age_s``, a
new track is born, and the object has two ids. The association's gates cannot simply be
widened for coasting tracks: a wide gate takes the neighbour too. This stage looks at the two
ends instead, once both are known:

* **lost tracks**: confirmed tracks the tracker dropped for being unseen too long
  (:meth:`Stitching.remember`; not those that left the located area, nor merged duplicates),
  predicted with the tracker's motion model. While a track still coasts the association may
  take it back; the stage leaves it to the association;
* **new tracks**: tentative tracks about to be confirmed, born after the lost track was last
  seen (two tracks seen at one instant are two objects) and within ``stitch_gap_s`` of it.

A new track continues a lost one when both clearly move (a track that stood still says
nothing of where it went) and they are alike where they meet: the new track's first position
(its state moved back along its velocity) against the lost track's last one moved across the
gap at the mean of their velocities, and the two velocities — the (x, y, vx, vy) difference
within ``stitch_sigmas`` of the sum of their covariances, and the positions within the
association's cap (``max_gate_m``). Only unambiguous pairs are joined: the new track has one
lost track within the test and that lost track no other tentative track that could be it. In a
crowd two people lost side by side are left apart (two new ids) rather than risk swapping
them; two cars are told apart by their velocities (opposite lanes, a car overtaking).

**Coasting people** (``stitch_coasting``). Where the cameras miss people hidden behind others
(the occlusion stage's learnt miss rate above one half: a crowd seen by a detector), a person
unseen by every camera for a second is often still there and walks off the coasting track's
prediction (they turned); the association's gate misses them when they reappear, a new track
is born and confirmed while the old one still coasts, and the person has two ids. The tracker
then also passes its coasting people's tracks (unseen now, not dropped yet) as ends: a new
track may continue one by the test above, or, when its velocity is not known yet (two cameras
confirmed it at once), by position alone: off the coasting track's prediction by no more than
a change of velocity of ``class_velocity_sigma`` (1.5 m/s for a person) takes a walker in the
time the track was unseen (:meth:`Stitching._within_reach`), and unambiguous as above. The
new track takes the id and the coasting track is dropped (:attr:`Stitches.replaced`). A new
track whose velocity is known may continue a coasting person who turned while hidden
(``stitch_turn_dps``, :meth:`Stitching._on_arc`): its position and heading now lie on the arc
of constant speed and turn rate from where the coasting track was last seen. Where
cameras see people through occlusion (annotated boxes), and for vehicles, a coasting track's
object is not hidden and the tracker passes none.

**Delay**: none by default. The decision is taken when the new track would be confirmed, with
its velocity as known then; a track confirmed before its velocity is known (two cameras see it
at once) is not stitched to a dropped track. With ``stitch_delay_s`` > 0 such a track, if a
lost track could be it, is held back (tentative, not reported) until its velocity is clearly
known or that long after its first detection. Either way ids are never rewritten: a row once
reported keeps its id, which is what the matcher service publishes and stores, and a
restarted or re-tracking service restores the lost tracks with the tracker's state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cblrs.matching import kalman
from cblrs.matching.fusion.state import table_from_state, table_state
from cblrs.matching.fusion.table import FusionContext, TrackTable


@dataclass
class Stitches:
    """What :meth:`Stitching.decide` decided for one window.

    Attributes:
        hold: (T,) bool, tentative tracks to keep tentative for now (they may continue a
            lost track; their velocity is not known well enough yet).
        rows: (K,) int64 rows of tentative tracks that continue a lost track.
        ids: (K,) int64 the id each of them takes.
        replaced: (J,) int64 rows of coasting tracks whose id a new track took (to drop).
    """

    hold: np.ndarray
    rows: np.ndarray
    ids: np.ndarray
    replaced: np.ndarray

    @classmethod
    def none(cls, count: int) -> Stitches:
        """Nothing to do for ``count`` tracks."""
        return cls(np.zeros(count, dtype=bool), np.zeros(0, np.int64), np.zeros(0, np.int64),
                   np.zeros(0, np.int64))


class Stitching:
    """The stitching stage of :class:`~cblrs.matching.fusion.tracker.FusionTracker`.

    It owns the lost tracks (confirmed tracks dropped for being unseen too long), predicts
    them like the tracker predicts its tracks, and decides which new tracks continue one.
    :meth:`decide` returns a :class:`Stitches`; it changes neither the table nor its input.

    Args:
        context: the tracker's configuration and motion models.
        class_acceleration: (K + 1,) white-noise acceleration of each class slot, m/s^2
            (the tracker's; the motion models scale it).
    """

    def __init__(self, context: FusionContext, class_acceleration: np.ndarray):
        self.context = context
        self.class_acceleration = np.asarray(class_acceleration, np.float64)
        self.reset()

    def reset(self) -> None:
        """Forget every lost track."""
        self.lost = TrackTable.empty(self.context.models, self.context.camera_count)
        self._time: float | None = None

    @property
    def enabled(self) -> bool:
        """Whether stitching is on (``stitch_gap_s`` > 0)."""
        return self.context.config.stitch_gap_s > 0

    def get_state(self) -> dict:
        """The lost tracks as JSON-ready data, restored by :meth:`set_state`."""
        return {"time": self._time, **table_state(self.lost)}

    def set_state(self, state: dict | None) -> None:
        """Restore :meth:`get_state`'s data (None: a state saved before this stage: none)."""
        self.reset()
        if state is None:
            return
        self._time = None if state["time"] is None else float(state["time"])
        self.lost = table_from_state(state, self.context.models, self.context.camera_count)

    def remember(self, ended: TrackTable, timestamp: float) -> None:
        """Keep confirmed tracks the tracker drops for being unseen too long.

        Args:
            ended: their rows, predicted to ``timestamp`` (tentative rows are ignored).
            timestamp: the window's time, seconds.
        """
        if not self.enabled:
            return
        self._advance(timestamp)
        confirmed = ended.ids >= 0
        if confirmed.any():
            self.lost = self.lost.extend(ended.select(confirmed))

    def decide(
        self, tracks: TrackTable, confirmable: np.ndarray, timestamp: float,
        coasting: np.ndarray | None = None,
    ) -> Stitches:
        """Which of the tracks about to be confirmed continue a lost track.

        Args:
            tracks: the table, predicted to ``timestamp`` and updated with this window.
            confirmable: (T,) bool, tentative tracks that would be confirmed now.
            timestamp: the window's time, seconds.
            coasting: (T,) bool, confirmed tracks unseen now that a new track may continue
                as well (``stitch_coasting``; None: none): the new track takes the id and
                the coasting track is dropped (``replaced``).

        Returns:
            The tracks to hold back, and the stitched tracks and the ids they take.
        """
        count = len(tracks)
        if not self.enabled:
            return Stitches.none(count)
        self._advance(timestamp)
        self._forget(tracks, timestamp)
        config = self.context.config
        ended = self.lost
        coasting_rows = np.zeros(0, np.int64)
        if coasting is not None and config.stitch_coasting:
            coasting_rows = np.flatnonzero(coasting & (tracks.ids >= 0))
            ended = ended.extend(tracks.select(coasting_rows))
        fresh = np.flatnonzero(tracks.ids < 0)  # every tentative track, for ambiguity
        if not len(ended) or not confirmable.any():
            return Stitches.none(count)

        candidates = tracks.select(fresh)
        possible = self._possible(ended, candidates, timestamp)  # (E, F) bool
        close = self._within_gate(ended, candidates, possible, timestamp)
        # Held until its velocity is clearly known, for at most the delay.
        young = (timestamp - candidates.born < config.stitch_delay_s) & ~_moving(candidates)
        if len(coasting_rows):
            # A coasting track is still in the table; a new track whose velocity is not known
            # yet may be it (the cameras lost the person, who walked off the prediction)
            # when it is no farther off than a change of velocity could have taken it.
            first = len(self.lost)
            coasting_ends = ended.select(np.arange(first, len(ended)))
            close[first:] |= self._within_reach(coasting_ends, candidates, timestamp) & (
                possible[first:])
            if config.stitch_turn_dps > 0:
                close[first:] |= self._on_arc(coasting_ends, candidates, timestamp) & (
                    possible[first:])
        # A young track's velocity is not known yet: it may be any lost track it could reach.
        rivals = close | (possible & young[None, :])
        stitches = Stitches.none(count)
        new = np.flatnonzero(confirmable[fresh])
        stitches.hold[fresh[new[possible[:, new].any(axis=0) & young[new]]]] = True
        rows, ids = [], []
        for column in new[(close[:, new].sum(axis=0) == 1) & ~young[new]].tolist():
            lost = int(np.flatnonzero(close[:, column])[0])
            if rivals[lost].sum() != 1:
                continue  # another tentative track could be it as well: leave both apart
            rows.append(fresh[column])
            ids.append(ended.ids[lost])
        taken = np.isin(self.lost.ids, ids)
        stitches.rows = np.asarray(rows, np.int64)
        stitches.ids = np.asarray(ids, np.int64)
        stitches.replaced = coasting_rows[np.isin(tracks.ids[coasting_rows], stitches.ids)]
        if taken.any():
            self.lost = self.lost.select(~taken)
        return stitches

    def _possible(self, ended: TrackTable, fresh: TrackTable, timestamp: float) -> np.ndarray:
        """(E, F) bool: which new tracks could continue which ended ones, their own velocity
        unknown.

        Same class, born after the ended track was last seen and within ``stitch_gap_s`` of
        it, the ended track clearly moving, and the new one near enough to the ended one's
        prediction that the test of :meth:`_within_gate` could pass: that test meets the two
        ends halfway across the gap, so with velocities that differ by three standard
        deviations of the ended track's, the new track may be off the prediction by the
        association's cap plus that difference over half the gap and the new track's age.
        """
        config = self.context.config
        gap = fresh.born[None, :] - ended.last_seen[:, None]
        age = timestamp - fresh.born
        cap = config.max_gate_m * self.context.class_scale[self.context.class_slot(ended.class_id)]
        reach = cap[:, None] + 3.0 * ended.velocity_sigma[:, None] * (0.5 * gap + age[None, :])
        distance = np.linalg.norm(fresh.state[None, :, :2] - ended.state[:, None, :2], axis=2)
        return (
            (ended.class_id[:, None] == fresh.class_id[None, :])
            & (gap > 0)
            & (gap <= config.stitch_gap_s)
            & _moving(ended)[:, None]
            & (distance <= reach)
        )

    def _within_reach(
        self, coasting: TrackTable, fresh: TrackTable, timestamp: float
    ) -> np.ndarray:
        """(K, F) bool: which new tracks whose velocity is not known yet are within reach of
        which coasting tracks: off the prediction by at most how far a change of velocity
        of ``class_velocity_sigma`` (a person's: 1.5 m/s) takes it in the time the
        coasting track was not seen, plus three standard deviations of the new track's
        position."""
        unseen = timestamp - coasting.last_seen
        speed = self.context.class_velocity_sigma[self.context.class_slot(coasting.class_id)]
        spread = np.sqrt(np.trace(fresh.covariance[:, :2, :2], axis1=1, axis2=2))
        reach = (speed * unseen)[:, None] + 3.0 * spread[None, :]
        distance = np.linalg.norm(
            fresh.state[None, :, :2] - coasting.state[:, None, :2], axis=2)
        return (distance <= reach) & ~_moving(fresh)[None, :]

    def _on_arc(self, coasting: TrackTable, fresh: TrackTable, timestamp: float) -> np.ndarray:
        """(K, F) bool: which moving new tracks a coasting person reached by turning.

        A walker hidden for a second often turns meanwhile (the crowd's people walk arcs);
        the coasting track goes straight on and the new track's velocity disagrees with it,
        so neither the gate test nor the reach of a change of velocity holds. Here the
        coasting track's last seen position and velocity are carried along the arc of
        constant speed (the mean of the two ends') and turn rate that ends in the new
        track's heading now; the new track must lie on it within three standard deviations
        of the two positions plus ``stitch_arc_m``, turn by at most ``stitch_turn_dps``
        degrees a second, and keep its speed (within three standard deviations of the two
        speeds).
        """
        config = self.context.config
        shape = (len(coasting), len(fresh))
        if not all(shape):
            return np.zeros(shape, dtype=bool)
        unseen = np.maximum(timestamp - coasting.last_seen, 1e-6)[:, None]  # (K, 1)
        old_velocity = coasting.state[:, None, 2:4]
        new_velocity = fresh.state[None, :, 2:4]
        last = coasting.state[:, None, :2] - old_velocity * unseen[..., None]
        old_speed = np.hypot(old_velocity[..., 0], old_velocity[..., 1])
        new_speed = np.hypot(new_velocity[..., 0], new_velocity[..., 1])
        heading = np.arctan2(old_velocity[..., 1], old_velocity[..., 0])
        turn = np.angle(np.exp(1j * (np.arctan2(new_velocity[..., 1], new_velocity[..., 0])
                                     - heading)))  # (K, F), in (-pi, pi]
        speed = 0.5 * (old_speed + new_speed)
        chord = speed * unseen * np.sinc(turn / (2.0 * np.pi))  # sin(t/2) / (t/2)
        direction = heading + 0.5 * turn
        arc_end = last + chord[..., None] * np.stack([np.cos(direction), np.sin(direction)], -1)
        error = np.linalg.norm(fresh.state[None, :, :2] - arc_end, axis=2)
        seen = (coasting.covariance[:, :2, :2] if coasting.seen_covariance is None
                else coasting.seen_covariance)  # (where it was when last seen)
        spread = np.sqrt(
            np.trace(fresh.covariance[:, :2, :2], axis1=1, axis2=2)[None, :]
            + np.trace(seen, axis1=1, axis2=2)[:, None]
        )
        speed_sigma = np.hypot(coasting.velocity_sigma[:, None], fresh.velocity_sigma[None, :])
        return (
            (error <= 3.0 * spread + config.stitch_arc_m)
            & (np.abs(turn) <= np.radians(config.stitch_turn_dps) * unseen)
            & (np.abs(new_speed - old_speed) <= 3.0 * speed_sigma)
            & _moving(fresh)[None, :]
        )

    def _within_gate(
        self, ended: TrackTable, fresh: TrackTable, possible: np.ndarray, timestamp: float
    ) -> np.ndarray:
        """(E, F) bool: which new tracks continue which ended ones, of the ``possible`` pairs.

        The new track clearly moving too, and the two alike where they meet: the new track's
        first position (its state moved back along its velocity) against the ended track's
        last one moved across the gap at the mean of their velocities, and the two
        velocities; the (x, y, vx, vy) difference within ``stitch_sigmas`` of the sum of
        their covariances now (the ended track's has grown with the time it was not seen),
        and the positions where they meet within the association's cap (``max_gate_m``,
        scaled with the class's size).
        """
        config = self.context.config
        gap = fresh.born[None, :] - ended.last_seen[:, None]
        possible = possible & _moving(fresh)[None, :]
        first, second = np.nonzero(possible)
        close = np.zeros(possible.shape, dtype=bool)
        if not len(first):
            return close
        # Comparing both predicted to now would stretch the ended track's velocity over the
        # gap and the new track's age; comparing where they meet uses each where it is known.
        ended_velocity, fresh_velocity = ended.state[first, 2:], fresh.state[second, 2:]
        last_position = (
            ended.state[first, :2] - ended_velocity * (timestamp - ended.last_seen[first])[:, None]
        )
        first_position = (
            fresh.state[second, :2] - fresh_velocity * (timestamp - fresh.born[second])[:, None]
        )
        difference = np.concatenate(
            [
                first_position
                - last_position
                - 0.5 * (ended_velocity + fresh_velocity) * gap[first, second][:, None],
                fresh_velocity - ended_velocity,
            ],
            axis=1,
        )
        covariance = fresh.covariance[second] + ended.covariance[first]
        distance = np.einsum(
            "ki,ki->k", difference, np.linalg.solve(covariance, difference[:, :, None])[:, :, 0]
        )
        # A track unseen for seconds may be anywhere by its covariance; where they meet, the
        # two ends must also be as close as the association's cap lets a detection be to
        # its track.
        cap = (
            config.max_gate_m
            * self.context.class_scale[self.context.class_slot(ended.class_id[first])]
        )
        close[first, second] = (distance <= config.stitch_sigmas**2) & (
            np.hypot(difference[:, 0], difference[:, 1]) <= cap
        )
        return close

    def _advance(self, timestamp: float) -> None:
        """Predict the lost tracks to ``timestamp``."""
        config = self.context.config
        if self._time is not None and timestamp > self._time and len(self.lost):
            lost = self.lost
            acceleration = self.class_acceleration[FusionContext.class_slot(lost.class_id)]
            lost.mode_state, lost.mode_covariance, lost.mode_probability = kalman.predict_models(
                lost.mode_state,
                lost.mode_covariance,
                lost.mode_probability,
                timestamp - self._time,
                acceleration[:, None] * np.asarray(config.model_acceleration_factors)[None],
                np.asarray(config.model_sojourn_s),
            )
            lost.state, lost.covariance = kalman.combine(
                lost.mode_state, lost.mode_covariance, lost.mode_probability
            )
        self._time = timestamp if self._time is None else max(self._time, timestamp)

    def _forget(self, tracks: TrackTable, timestamp: float) -> None:
        """Forget the lost tracks no new track can continue any more: lost longer than
        ``stitch_gap_s`` ago, and no tentative track (one may wait for a second camera
        to confirm it) born within the gap after they were last seen."""
        if not len(self.lost):
            return
        gap = self.context.config.stitch_gap_s
        keep = timestamp - self.lost.last_seen <= gap
        if not keep.all():
            born = tracks.born[tracks.ids < 0]
            after = born[None, :] - self.lost.last_seen[:, None]
            keep |= ((after > 0) & (after <= gap)).any(axis=1)
            self.lost = self.lost.select(keep)


def _moving(tracks: TrackTable) -> np.ndarray:
    """(T,) bool: tracks whose speed is clearly known (above three standard deviations of
    their velocity when last seen).

    Only such ends are stitched: their directions can agree or not. Where one stood still
    its end says nothing of where it went, and anyone appearing nearby within the gap
    would fit it.
    """
    speed = np.hypot(tracks.state[:, 2], tracks.state[:, 3])
    return speed > 3.0 * tracks.velocity_sigma
