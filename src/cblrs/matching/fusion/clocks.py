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
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable

logger = logging.getLogger(__name__)

_CORROBORATION_S = 2.0  # a track seen by another camera this recently corroborates a view


class ClockLearning:
    """What :class:`~cblrs.matching.fusion.tracker.FusionTracker` tells its clock model.

    Args:
        context: the tracker's configuration and cameras.
        clock: the camera-clock model it feeds (the tracker's).
    """

    def __init__(self, context: FusionContext, clock: ClockModel):
        self.context = context
        self.clock = clock
        self.turn = 0  # which share of a crowd's tracks the clock learns from next

    def reset(self) -> None:
        """Forget the rotation (the clock model is reset by its owner)."""
        self.turn = 0

    def learn(
        self, tracks: TrackTable, measured: Measured, observed: Observations,
        covariance: np.ndarray, matched: np.ndarray, rows: np.ndarray, timestamp: float,
    ) -> None:
        """Count corroborated views and queue views for the clock model (before the update).

        Only views of confirmed tracks that another camera saw recently count: a track seen
        by one camera alone follows that camera's clock and says nothing about it.
        """
        if self.context.camera_count < 2 or not self.context.config.estimate_clocks:
            return  # one camera: nothing to compare its clock with
        camera = observed.camera[matched]
        recent = tracks.seen_by[rows] >= timestamp - _CORROBORATION_S
        recent[np.arange(len(rows)), camera] = False
        corroborated = recent.any(axis=1) & (tracks.ids[rows] >= 0)
        if len(camera) == len(matched):  # every detection has a track
            self.clock.corroboration(camera, corroborated)
        else:
            self.clock.corroboration(
                np.concatenate([camera, observed.camera[~matched]]),
                np.concatenate([corroborated, np.zeros(int((~matched).sum()), dtype=bool)]),
            )
        if not corroborated.any():
            return
        use = np.flatnonzero(corroborated)
        ids = tracks.ids[rows[use]]
        share = -(-len(use) // self.clock.view_budget)  # ceil
        if share > 1:
            # A crowd gives more evidence than needed: learn from a rotating share of its
            # tracks (whole tracks: a view is compared with the same track's other views).
            use = use[ids % share == self.turn % share]
            self.turn += 1
        track_rows = rows[use]
        views = np.flatnonzero(matched)[use]
        direction = measured.direction[views]
        across = None
        if np.isfinite(self.context.camera_xy[camera[use], 0]).all():
            across = np.column_stack([-direction[:, 1], direction[:, 0]])
        self.clock.add_views(
            camera[use], track_rows, observed.world_xy[views], covariance[views],
            tracks.state[track_rows, 2:4], across, tracks.state[track_rows, :2],
            tracks.covariance[track_rows, :2, :2] + self.context.object_covariance,
        )

    def record(
        self, tracks: TrackTable, timestamp: float, shown: np.ndarray, located_xy: np.ndarray,
        camera: np.ndarray, raw_time_of_camera: np.ndarray,
    ) -> None:
        """End the window for the clock model: tracks and views for its coarse search."""
        if not self.context.config.estimate_clocks or self.context.camera_count < 2:
            return  # one camera: nothing to compare its clock with
        recent = tracks.seen_by[shown] >= timestamp - _CORROBORATION_S
        sole = np.where(recent.sum(axis=1) == 1, np.argmax(recent, axis=1), -1)
        self.clock.record(timestamp, tracks.state[shown, :2], sole.astype(np.int64),
                           camera, located_xy, raw_time_of_camera[camera])
        for event in self.clock.end_window(timestamp):
            name = self.context.camera_ids[event.camera]
            if event.kind == "back":
                logger.info("camera %s: clock back within %.3f s of the others (%+.3f s)",
                            name, self.context.config.clock_tolerance_s, event.offset_s)
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
