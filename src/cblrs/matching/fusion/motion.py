"""Motion check after association (step 4b of the fusion tracker's update): vehicles cannot
turn on the spot.

A gate in the prediction's frame is a round (or ray-shaped) region; for a car coasting out of
the covered area it reaches across the road, and the next car arriving on the opposite lane,
3-4 m away and moving the other way, falls inside it: one id would then cover two cars and
every origin-destination count built on it goes wrong. A vehicle, unlike a person, follows
arcs no tighter than its turning radius ``R`` (:attr:`FusionConfig.class_turn_radius_m`):
moving at speed ``s``, ``t`` seconds after it was last seen, the direction from where it was
to where it is now differs from its heading by at most ``s t / (2 R)`` (the chord of the
tightest arc), and it cannot have reversed.

:class:`MotionCheck` tests each track's detections of this instant, fused (several views
average out the offsets of single boxes), against that cone: when the fused position lies
farther from the cone than ``gate_sigmas`` standard deviations of its noise, the track did not
make that move; its detections are released (they start a track of their own at the birth
step) and the track coasts. Only tracks whose speed is known (at least 1 m/s and three
standard deviations) are checked; people, stopped vehicles and new tracks are not.

When single views are too noisy for that test to be sure (a car's box bottom is not its
footprint), a wrong hand-over still shows a moment later: the track's velocity settles in a
direction it could not have turned to. :meth:`MotionCheck.split` compares each vehicle
track's direction, whenever it is well known, with the last direction that was well known;
a turn sharper than the turning radius allows in the time between (beyond the two
directions' uncertainties) is a second object taking the track over, and the track is given
a new id from then on. The delay is the time the velocity takes to settle (under a second
at 10 fps); rows already reported keep their id.
"""

from __future__ import annotations

import numpy as np

from cblrs.matching.base import Observations
from cblrs.matching.fusion.gaussian import fuse
from cblrs.matching.fusion.reachable import ReachableCone
from cblrs.matching.fusion.table import FusionContext, TrackTable


class MotionCheck:
    """Releases the detections of vehicle tracks that would have to turn too sharply.

    Inputs: the tracks predicted to the window's time, the window's detections and their
    assignment; output: the assignment with the detections of impossible moves set to -1.

    Args:
        context: the tracker's configuration and per-class turning radii.
    """

    def __init__(self, context: FusionContext):
        self.context = context
        self.cone = ReachableCone(context)

    def turn_limits(
        self, tracks: TrackTable, timestamp: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where each track's cone starts, its heading, how far it can have turned, and the
        start's covariance (:meth:`ReachableCone.limits`)."""
        return self.cone.limits(tracks, timestamp)

    def check(
        self,
        tracks: TrackTable,
        observed: Observations,
        covariance: np.ndarray,
        assigned: np.ndarray,
        timestamp: float,
    ) -> np.ndarray:
        """``assigned`` with the detections of tracks that cannot have moved there set to -1.

        Args:
            tracks: the tracks, predicted to ``timestamp``.
            observed: the window's detections (N rows).
            covariance: (N, 2, 2) their covariances, square metres.
            assigned: (N,) int64 track row of each detection (-1: none).
            timestamp: the window's time, seconds.
        """
        matched = assigned >= 0
        if not matched.any():
            return assigned
        context = self.context
        if not np.isfinite(context.class_turn_radius[context.class_slot(tracks.class_id)]).any():
            return assigned  # no track of a class with a turning radius: no cone to leave
        anchor, heading, limit, anchor_covariance = self.turn_limits(tracks, timestamp)
        rows = assigned[matched]
        checked = np.isfinite(limit)
        if not checked[rows].any():
            return assigned
        fused_xy, fused_covariance, seen = fuse(
            rows, len(tracks), observed.world_xy[matched], covariance[matched]
        )
        candidates = np.flatnonzero(seen & checked)
        sigmas = self.cone.outside(
            anchor[candidates],
            heading[candidates],
            limit[candidates],
            fused_xy[candidates],
            fused_covariance[candidates] + anchor_covariance[candidates],
        )
        impossible = candidates[sigmas > self.context.config.gate_sigmas]
        if len(impossible) == 0:
            return assigned
        released = assigned.copy()
        released[np.isin(assigned, impossible)] = -1
        return released

    def split(self, tracks: TrackTable, seen_now: np.ndarray, timestamp: float) -> np.ndarray:
        """(T,) bool: vehicle tracks whose direction turned further than they can turn.

        Also records each well-known direction in ``tracks`` (``heading``, ``heading_time``,
        ``heading_sigma``, with where the track was and its speed: ``heading_xy``,
        ``heading_speed``) for the next call and for the reachable cone of a track whose
        motion is no longer well known.

        Args:
            tracks: the tracks after this instant's update.
            seen_now: (T,) bool, the tracks updated at this instant.
            timestamp: the window's time, seconds.
        """
        count = len(tracks)
        turned = np.zeros(count, dtype=bool)
        radius = self.context.class_turn_radius[self.context.class_slot(tracks.class_id)]
        velocity = tracks.state[:, 2:4]
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        known = (
            seen_now & np.isfinite(radius) & (speed >= np.maximum(1.0, 3.0 * tracks.velocity_sigma))
        )
        if not known.any():
            return turned
        heading = velocity[known] / speed[known, None]
        sigma = tracks.velocity_sigma[known] / speed[known]
        before = np.isfinite(tracks.heading_time[known])
        elapsed = timestamp - tracks.heading_time[known]
        cosine = np.clip(np.einsum("ij,ij->i", heading, tracks.heading[known]), -1.0, 1.0)
        allowed = speed[known] * np.where(before, elapsed, 0.0) / radius[known] + 3.0 * (
            sigma + tracks.heading_sigma[known]
        )
        turned[np.flatnonzero(known)[before & (np.arccos(cosine) > allowed)]] = True
        tracks.heading[known] = heading
        tracks.heading_time[known] = timestamp
        tracks.heading_sigma[known] = sigma
        tracks.heading_xy[known] = tracks.state[known, :2]
        tracks.heading_speed[known] = speed[known]
        return turned
