"""What the fusion tracker tells its camera-clock model (:mod:`cblrs.matching.clock`).

Views of confirmed tracks that other cameras corroborate are queued for the fine estimate of
each camera's offset; at the end of each window the tracks and views go to the coarse search.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from cblrs.matching.base import (
    Observations,
)
from cblrs.matching.clock import ClockModel
from cblrs.matching.fusion.state import STATE_VERSION
from cblrs.matching.fusion.table import TrackTable

logger = logging.getLogger(__name__)

_CORROBORATION_S = 2.0  # a track seen by another camera this recently corroborates a view


class ClockLearning(TrackTable):
    """The clock-learning steps of :class:`~cblrs.matching.fusion.tracker.FusionTracker` (a mixin).
    """

    def _learn_clocks(
        self, observed: Observations, covariance: np.ndarray, matched: np.ndarray,
        rows: np.ndarray, timestamp: float,
    ) -> None:
        """Count corroborated views and queue views for the clock model (before the update).

        Only views of confirmed tracks that another camera saw recently count: a track seen
        by one camera alone follows that camera's clock and says nothing about it.
        """
        if len(self.camera_ids) < 2 or not self.config.estimate_clocks:
            return  # one camera: nothing to compare its clock with
        camera = observed.camera[matched]
        recent = self._seen_by[rows] >= timestamp - _CORROBORATION_S
        recent[np.arange(len(rows)), camera] = False
        corroborated = recent.any(axis=1) & (self._ids[rows] >= 0)
        self._clock.corroboration(
            np.concatenate([camera, observed.camera[~matched]]),
            np.concatenate([corroborated, np.zeros(int((~matched).sum()), dtype=bool)]),
        )
        if not corroborated.any():
            return
        use = np.flatnonzero(corroborated)
        ids = self._ids[rows[use]]
        share = -(-len(use) // self._clock.view_budget)  # ceil
        if share > 1:
            # A crowd gives more evidence than needed: learn from a rotating share of its
            # tracks (whole tracks: a view is compared with the same track's other views).
            use = use[ids % share == self._clock_turn % share]
            self._clock_turn += 1
        tracks = rows[use]
        direction = self._direction[matched][use]
        across = None
        if np.isfinite(self._camera_xy[camera[use], 0]).all():
            across = np.column_stack([-direction[:, 1], direction[:, 0]])
        self._clock.add_views(
            camera[use], tracks, observed.world_xy[matched][use], covariance[matched][use],
            self._state[tracks, 2:4], across, self._state[tracks, :2],
            self._covariance[tracks, :2, :2] + self._object_covariance,
        )

    def _record_for_clocks(
        self, timestamp: float, shown: np.ndarray, located_xy: np.ndarray,
        camera: np.ndarray, raw_time_of_camera: np.ndarray,
    ) -> None:
        """End the window for the clock model: tracks and views for its coarse search."""
        if not self.config.estimate_clocks or len(self.camera_ids) < 2:
            return  # one camera: nothing to compare its clock with
        recent = self._seen_by[shown] >= timestamp - _CORROBORATION_S
        sole = np.where(recent.sum(axis=1) == 1, np.argmax(recent, axis=1), -1)
        self._clock.record(timestamp, self._state[shown, :2], sole.astype(np.int64),
                           camera, located_xy, raw_time_of_camera[camera])
        for event in self._clock.end_window(timestamp):
            name = self.camera_ids[event.camera]
            if event.kind == "back":
                logger.info("camera %s: clock back within %.3f s of the others (%+.3f s)",
                            name, self.config.clock_tolerance_s, event.offset_s)
            else:
                logger.warning(
                    "camera %s: clock off by %+.3f s against the other cameras%s; its "
                    "timestamps are corrected", name, event.offset_s,
                    " (found by searching)" if event.kind == "jump" else "",
                )


def clock_report(state: dict | None, camera_ids: Sequence[str]) -> dict[str, Any] | None:
    """The clock report (:meth:`FusionTracker.clock_report`) of a saved fusion-tracker state.

    Returns:
        None for a state of another matcher (or none).
    """
    if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
        return None
    clock = ClockModel(len(camera_ids))
    try:
        clock.set_state(state["clock"])
    except (KeyError, TypeError, ValueError):
        return None
    return clock.report(camera_ids)
