"""Where a vehicle can be: the reachable cone of a moving track, and tests against it.

A vehicle, unlike a person, follows arcs no tighter than its turning radius ``R``
(:attr:`FusionConfig.class_turn_radius_m`) and does not reverse while moving: ``t`` seconds
after it was last seen at speed ``s``, the direction from where it was (the *anchor*) to where
it is now differs from its heading by at most ``s t / (2 R)`` (the chord of the tightest arc).
That cone is what a car coasting out of the covered area can reach; the next car arriving on
the opposite lane, 3-4 m to its side and moving the other way, lies outside it.

How far outside is measured in the noise of the position tested, *along the direction that
separates it from the cone*: a view of a car is metres uncertain along its camera's ray but
much less across it, and an oncoming car 4 m to the side of a car driving along a camera's
ray is far outside in that camera's precise direction even though it is within four of the
ray's standard deviations. (The largest standard deviation, used before, let a coasting car
take the oncoming one whenever a view looked along the road.)

:class:`ReachableCone` is used twice by the fusion tracker: the association gate drops
detection-track pairs outside the cone (:meth:`ReachableCone.feasible`, so the assignment
looks for the detection's own track instead), and the motion check tests each track's fused
position of the instant (:mod:`cblrs.matching.fusion.motion`). Only vehicle tracks whose
speed is well known (at least 1 m/s and three standard deviations) are tested, now or, when a
wrong view has thrown their velocity off, at their last well-known motion (see
:meth:`ReachableCone.limits`); people, stopped vehicles and new tracks never are. The cone
starts at the track's estimate when last seen, whose uncertainty is added to the position's.
"""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.fusion.table import FusionContext, TrackTable

_MIN_SPEED_MPS = 1.0  # slower than this a heading means little (a car creeping in a queue)


class ReachableCone:
    """The reachable cone of each vehicle track and the normalised distance to it.

    Args:
        context: the tracker's configuration and per-class turning radii.
    """

    def __init__(self, context: FusionContext):
        self.context = context
        config = context.config
        # (K + 1,) per class (last: unknown), m/s^2: how much faster than its last
        # well-known speed a track may have driven since.
        self.acceleration = np.array(
            [
                config.class_acceleration_sigma.get(name, config.acceleration_sigma)
                for name in CLASS_NAMES
            ]
            + [config.acceleration_sigma]
        )

    def limits(
        self, tracks: TrackTable, timestamp: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where each track's cone starts, its axis, how far the track can have turned, and
        how uncertain the start is.

        A track whose velocity is well known now is held to its cone from where it was last
        seen. One whose velocity is no longer well known (a wrong view taken while coasting
        throws it off: the next car on the opposite lane drags it sideways and its
        uncertainty grows) is still held to the cone of its last well-known motion, widened
        by the path it can have driven since (that speed, and the class's acceleration):
        so the second car's next views are released although the first one was taken.

        Args:
            tracks: the tracks, predicted to ``timestamp``.
            timestamp: the time tested, seconds.

        Returns:
            ``(anchor (T, 2) metres, heading (T, 2) unit vectors, limit (T,) radians (inf:
            not tested), anchor covariance (T, 2, 2) square metres)``. The start of a cone
            is the track's estimate when last seen, which lags a car that brakes hard: its
            uncertainty is added to that of the positions tested. (Not the prediction's:
            that grows while the track coasts, in every direction, and a car does not.)
        """
        count = len(tracks)
        limit = np.full(count, np.inf)
        slot = self.context.class_slot(tracks.class_id)
        radius = self.context.class_turn_radius[slot]
        velocity = tracks.state[:, 2:4]
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        speed_sigma = tracks.velocity_sigma  # when last seen: coasting does not forget it
        elapsed = np.maximum(timestamp - tracks.last_seen, 0.0)
        known = np.isfinite(radius) & (speed >= np.maximum(_MIN_SPEED_MPS, 3.0 * speed_sigma))
        limit[known] = np.minimum(speed[known] * elapsed[known] / (2.0 * radius[known]), np.pi)
        heading = velocity / np.maximum(speed, 1e-12)[:, None]
        anchor = tracks.state[:, :2] - velocity * elapsed[:, None]
        anchor_covariance = tracks.seen_covariance.copy()
        recorded = (
            np.isfinite(radius)
            & ~known
            & np.isfinite(tracks.heading_time)
            & np.isfinite(tracks.heading_xy).all(axis=1)
            & (tracks.heading_speed >= _MIN_SPEED_MPS)
        )
        if recorded.any():
            since = np.maximum(timestamp - tracks.heading_time[recorded], 0.0)
            path = (
                tracks.heading_speed[recorded] * since
                + 0.5 * self.acceleration[slot[recorded]] * since**2
            )
            limit[recorded] = np.minimum(
                path / (2.0 * radius[recorded]) + 3.0 * tracks.heading_sigma[recorded], np.pi
            )
            anchor[recorded] = tracks.heading_xy[recorded]
            heading[recorded] = tracks.heading[recorded]
            # Estimated when the motion was well known; the prediction since says nothing of it.
            anchor_covariance[recorded] = 0.0
        return anchor, heading, limit, anchor_covariance

    def outside(
        self,
        anchor: np.ndarray,
        heading: np.ndarray,
        limit: np.ndarray,
        xy: np.ndarray,
        covariance: np.ndarray,
    ) -> np.ndarray:
        """(K,) how many standard deviations each position lies outside its cone (0: inside).

        Args:
            anchor: (K, 2) apex of each cone, metres.
            heading: (K, 2) unit axis of each cone.
            limit: (K,) half-angle of each cone, radians (finite).
            xy: (K, 2) positions tested, metres.
            covariance: (K, 2, 2) their covariances; the object's own extent is added.
        """
        offset = xy - anchor
        distance = np.hypot(offset[:, 0], offset[:, 1])
        unit = offset / np.maximum(distance, 1e-12)[:, None]
        cosine = np.clip(np.einsum("ij,ij->i", unit, heading), -1.0, 1.0)
        excess = np.arccos(cosine) - limit
        # Beyond a right angle from the cone's edge the nearest point of the cone is its apex.
        behind = excess >= np.pi / 2
        gap = np.where(excess <= 0, 0.0, np.where(behind, distance, distance * np.sin(excess)))
        # The direction from the nearest point of the cone to the position: across the edge
        # (the offset turned back by the excess angle, then a quarter turn away from the
        # axis), or straight from the apex when behind it.
        side = np.sign(heading[:, 0] * unit[:, 1] - heading[:, 1] * unit[:, 0])
        side = np.where(side == 0, 1.0, side)
        edge_angle = np.arctan2(heading[:, 1], heading[:, 0]) + side * (limit + np.pi / 2)
        normal = np.where(
            behind[:, None], unit, np.column_stack([np.cos(edge_angle), np.sin(edge_angle)])
        )
        spread = covariance + self.context.object_covariance
        variance = np.einsum("ki,kij,kj->k", normal, spread, normal)
        return gap / np.sqrt(np.maximum(variance, 1e-12))

    def feasible(
        self,
        tracks: TrackTable,
        timestamp: float,
        columns: np.ndarray,
        xy: np.ndarray,
        covariance: np.ndarray,
        limits: tuple[np.ndarray, ...] | None = None,
    ) -> np.ndarray:
        """(K,) bool: each position is within ``gate_sigmas`` of its track's cone.

        Args:
            tracks: the tracks, predicted to ``timestamp``.
            timestamp: the time of the positions, seconds.
            columns: (K,) track row of each position.
            xy: (K, 2) positions, metres.
            covariance: (K, 2, 2) their covariances.
            limits: :meth:`limits` of ``tracks`` at ``timestamp`` when already computed (an
                association gates several times per instant).
        """
        ok = np.ones(len(columns), dtype=bool)
        if len(columns) == 0:
            return ok
        anchor, heading, limit, anchor_covariance = (
            self.limits(tracks, timestamp) if limits is None else limits
        )
        tested = np.flatnonzero(np.isfinite(limit[columns]))
        if len(tested) == 0:
            return ok
        rows = columns[tested]
        sigmas = self.outside(
            anchor[rows],
            heading[rows],
            limit[rows],
            xy[tested],
            covariance[tested] + anchor_covariance[rows],
        )
        ok[tested] = sigmas <= self.context.config.gate_sigmas
        return ok
