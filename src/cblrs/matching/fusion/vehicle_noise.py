"""How precisely a vehicle is located once its footprint centre is known (step 5 of the
fusion tracker's update, for vehicles).

Before association a vehicle detection's footprint centre is a guess averaged over headings
(:mod:`~cblrs.matching.fusion.footprint`): a car's box bottom may lie anywhere from 0.9 to
2.25 m short of its centre, so its noise carries the class's extra sigma
(:attr:`~cblrs.matching.fusion.config.FusionConfig.class_measurement_sigma_m`, 0.7 m for a
car), which keeps the gates wide enough to take it. Once the detection is given a track
whose heading is known, the footprint stage moves it with that heading, and what is left is
the cameras' own error, typically a tenth of that. Updating the filter with the wide noise
anyway makes it trust its constant-velocity prediction over the views: on a roundabout's
ring, where a car turns all the time, the reported position then lags and drifts outward by
tenths of a metre while the fused views are within one.

:class:`VehicleNoise` learns that remaining error like the noise model learns people's
(:class:`~cblrs.matching.fusion.noise.NoiseModel`: from how much the cameras that see one
vehicle disagree, along and across their rays, growing with distance) from the refined
detections only, and gives the refined detections that covariance for the filter update,
never sharper than ``vehicle_minimum_sigma_m`` (0.3 m) per view: cameras that agree within
centimetres still share the error of a class-typical footprint and of a lagging heading,
which their disagreement cannot show. Association, the motion check and births still use
the wide noise: only the estimate of where a tracked vehicle is gets sharper, not which
detections it may take.
"""

from __future__ import annotations

import numpy as np

from cblrs.arrays import unique_integers
from cblrs.detections import CLASS_NAMES
from cblrs.matching.fusion.gaussian import fuse, ray_covariance
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable
from cblrs.matching.fusion.turning import TurnFilter


class VehicleNoise:
    """The learned noise of vehicle detections refined with their track's heading.

    Args:
        context: the tracker's configuration (the noise prior: ``measurement_sigma_m``,
            ``along_sigma_per_distance``, ``sigma_per_distance``; the floor
            ``minimum_sigma_m``) and per-class extra sigmas (classes with one are vehicles).
        enabled: False leaves every covariance as it is (the footprint stage is off).

    Example:
        >>> from cblrs.matching.fusion.config import FusionConfig
        >>> context = FusionContext(FusionConfig(), ["a"], np.zeros((1, 2)),
        ...                         np.zeros(9), np.ones(9), NoiseModel(0.2, 0.01))
        >>> VehicleNoise(context).model.sigma_m
        0.2
    """

    def __init__(self, context: FusionContext, enabled: bool = True):
        self.context = context
        self.enabled = enabled
        config = context.config
        # One model per class slot: a bus's box, and its error, are larger than a car's.
        self.models = [NoiseModel(config.measurement_sigma_m, config.along_sigma_per_distance,
                                  config.sigma_per_distance)
                       for _ in range(len(context.class_extra))]
        self.turning = TurnFilter(context)

    @property
    def model(self) -> NoiseModel:
        """The model of cars."""
        return self.models[CLASS_NAMES.index("car")]

    def reset(self) -> None:
        """Forget what was learnt."""
        for model in self.models:
            model.reset()

    def refined(
        self, tracks: TrackTable, class_id: np.ndarray, assigned: np.ndarray
    ) -> np.ndarray:
        """(N,) bool: vehicle detections given a track whose heading is known (those the
        footprint stage moved with that heading)."""
        refined = np.zeros(len(assigned), dtype=bool)
        if not self.enabled or not len(assigned):
            return refined
        matched = np.flatnonzero(assigned >= 0)
        rows = assigned[matched]
        known = np.isfinite(tracks.heading_time[rows]) & (np.hypot(*tracks.heading[rows].T) > 0)
        vehicle = self.context.class_extra[FusionContext.class_slot(class_id[matched])] > 0
        refined[matched[known & vehicle]] = True
        return refined

    def learn(
        self, world_xy: np.ndarray, measured: Measured, refined: np.ndarray,
        assigned: np.ndarray, class_id: np.ndarray,
    ) -> None:
        """Learn from the refined detections' disagreement per track.

        Args:
            world_xy: (N, 2) the detections at the window's time, metres.
            measured: their rays and distances.
            refined: (N,) bool, from :meth:`refined`.
            assigned: (N,) int64 track row of each detection.
            class_id: (N,) their classes (each class's noise is learned apart).
        """
        if refined.sum() < 2:
            return
        slot = FusionContext.class_slot(class_id)
        for index in unique_integers(slot[refined]).tolist():
            self.models[index].learn(world_xy, measured.distance,
                                     np.where(refined & (slot == index), assigned, -1),
                                     measured.direction, measured.along_distance)

    def locate(
        self, tracks: TrackTable, world_xy: np.ndarray, measured: Measured,
        refined: np.ndarray, lag_covariance: np.ndarray, assigned: np.ndarray,
        class_id: np.ndarray, timestamp: float,
    ) -> np.ndarray:
        """(T, 2) where each track with refined detections is, NaN for the others.

        The refined detections of a track are fused under the learned noise (plus what
        their capture lag adds, ``lag_covariance``) and given to the track's turning filter
        (:class:`~cblrs.matching.fusion.turning.TurnFilter`, started from the track's
        prediction before its update; cars) or correct that prediction, as a Kalman update
        would (other vehicles); the tracker's filter itself is left to its update with the
        wide noise, so association is unchanged.

        Args:
            tracks: the tracks, predicted to the window's time and not yet updated (their
                turning filters are updated in place).
            world_xy: (N, 2) the detections at the window's time, metres.
            measured: their rays and distances.
            refined: (N,) bool, from :meth:`refined`.
            lag_covariance: (N, 2, 2) added to each detection's noise for its capture lag.
            assigned: (N,) int64 track row of each detection.
            class_id: (N,) their classes.
            timestamp: the window's time, seconds.
        """
        located = np.full((len(tracks), 2), np.nan)
        if not refined.any():
            return located
        along = np.zeros(int(refined.sum()))
        lateral = np.zeros(int(refined.sum()))
        slot = FusionContext.class_slot(class_id[refined])
        for index in unique_integers(slot).tolist():
            mine = slot == index
            along[mine], lateral[mine] = self.models[index].variances(
                measured.distance[refined][mine], measured.along_distance[refined][mine])
        config = self.context.config
        floor = max(config.minimum_sigma_m, config.vehicle_minimum_sigma_m) ** 2
        noise = ray_covariance(measured.direction[refined], np.maximum(along, floor),
                               np.maximum(lateral, floor)) + lag_covariance[refined]
        fused_xy, fused_covariance, seen = fuse(assigned[refined], len(tracks),
                                                world_xy[refined], noise)
        rows = np.flatnonzero(seen)
        turning = self.turning.applies(tracks.class_id[rows])
        # A turning model needs a heading: a car that is not clearly moving (stopped at a
        # light, queueing) keeps each instant's correction, and its filter starts afresh.
        speed = np.hypot(tracks.state[rows, 2], tracks.state[rows, 3])
        moving = speed >= np.maximum(1.0, 3.0 * tracks.velocity_sigma[rows])
        tracks.turn_state[rows[turning & ~moving]] = np.nan
        turning &= moving
        filtered = rows[turning]
        located[filtered] = self.turning.locate(tracks, filtered, fused_xy[filtered],
                                                fused_covariance[filtered], timestamp)
        # Other vehicles: the track's prediction corrected by this instant's views alone.
        other = rows[~turning]
        prior = tracks.state[other, :2]
        prior_covariance = tracks.covariance[other, :2, :2]
        total = prior_covariance + fused_covariance[other] + self.context.object_covariance
        gain = prior_covariance @ np.linalg.inv(total)
        located[other] = prior + np.einsum("kij,kj->ki", gain, fused_xy[other] - prior)
        return located

    @staticmethod
    def position(tracks: TrackTable, rows: np.ndarray, timestamp: float) -> np.ndarray:
        """(K, 2) the position to report for ``rows`` at the window's time: where they were
        located at this instant when that is known, else the filter's estimate."""
        position = tracks.state[rows, :2].copy()
        located = tracks.located[rows]
        use = np.isfinite(located[:, 0]) & (tracks.last_seen[rows] == timestamp)
        position[use] = located[use]
        return position

    def get_state(self) -> dict:
        """The learnt models as JSON-ready data."""
        return {"models": [model.get_state() for model in self.models]}

    def set_state(self, state: dict | None) -> None:
        """Restore :meth:`get_state` (None: start afresh, a state saved before this stage)."""
        self.reset()
        for model, saved in zip(self.models, (state or {}).get("models", []), strict=False):
            model.set_state(saved)
