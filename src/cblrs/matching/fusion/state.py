"""Snapshots of the fusion tracker's track table, as plain JSON-able data.

:meth:`FusionTracker.get_state` / :meth:`FusionTracker.set_state` save and restore the whole
tracker (versioned by :data:`STATE_VERSION`; a state saved by a matcher restores in a new one,
the matcher service's autosave); the track table's part is here.
"""

from __future__ import annotations

import math

import numpy as np

from cblrs.matching.base import MatcherError
from cblrs.matching.fusion.table import TrackTable

STATE_VERSION = "cblrs.fusion-tracker/5"


def table_state(tracks: TrackTable) -> dict:
    """The track table as JSON-ready data (keys of the tracker's saved state)."""
    return {
        "ids": tracks.ids.tolist(),
        "class_id": tracks.class_id.tolist(),
        "state": tracks.state.tolist(),
        "covariance": tracks.covariance.tolist(),
        "evidence": tracks.evidence.tolist(),
        "last_seen": tracks.last_seen.tolist(),
        "mode_state": tracks.mode_state.tolist(),
        "mode_covariance": tracks.mode_covariance.tolist(),
        "mode_probability": tracks.mode_probability.tolist(),
        "seen_by": [[value if math.isfinite(value) else None for value in row]
                    for row in tracks.seen_by.tolist()],
        "velocity_sigma": tracks.velocity_sigma.tolist(),
        "heading": tracks.heading.tolist(),
        "heading_time": [value if math.isfinite(value) else None
                         for value in tracks.heading_time.tolist()],
        "heading_sigma": tracks.heading_sigma.tolist(),
        "heading_xy": [[value if math.isfinite(value) else None for value in row]
                       for row in tracks.heading_xy.tolist()],
        "heading_speed": tracks.heading_speed.tolist(),
        "seen_covariance": tracks.seen_covariance.tolist(),
        "born": tracks.born.tolist(),
        "support_seen": tracks.support_seen.tolist(),
        "support_covered": tracks.support_covered.tolist(),
        # Vehicles' turning filters (NaN / -inf: none yet).
        "turn_state": [[value if math.isfinite(value) else None for value in row]
                       for row in tracks.turn_state.tolist()],
        "turn_covariance": tracks.turn_covariance.tolist(),
        "turn_time": [value if math.isfinite(value) else None
                      for value in tracks.turn_time.tolist()],
    }


def table_from_state(state: dict, models: int, cameras: int) -> TrackTable:
    """The track table saved by :func:`table_state`.

    Raises:
        KeyError, TypeError, ValueError, IndexError: a missing or malformed column.
        MatcherError: columns of different lengths.
    """
    covariance = np.asarray(state["covariance"], np.float64).reshape(-1, 4, 4)
    # States saved before velocity_sigma existed: the current velocity uncertainty.
    velocity_sigma = state.get("velocity_sigma")
    if velocity_sigma is None:
        velocity_sigma = np.sqrt(np.maximum(covariance[:, 2, 2] + covariance[:, 3, 3], 0.0))
    count = len(covariance)
    heading_time = state.get("heading_time", [None] * count)
    tracks = TrackTable(
        ids=np.asarray(state["ids"], np.int64).reshape(-1),
        class_id=np.asarray(state["class_id"], np.int64).reshape(-1),
        state=np.asarray(state["state"], np.float64).reshape(-1, 4),
        covariance=covariance,
        mode_state=np.asarray(state["mode_state"], np.float64).reshape(-1, models, 4),
        mode_covariance=np.asarray(state["mode_covariance"], np.float64).reshape(
            -1, models, 4, 4),
        mode_probability=np.asarray(state["mode_probability"], np.float64).reshape(-1, models),
        evidence=np.asarray(state["evidence"], np.int64).reshape(-1),
        last_seen=np.asarray(state["last_seen"], np.float64).reshape(-1),
        seen_by=np.array(
            [[-np.inf if value is None else value for value in row]
             for row in state["seen_by"]], np.float64,
        ).reshape(-1, cameras),
        velocity_sigma=np.asarray(velocity_sigma, np.float64).reshape(-1),
        heading=np.asarray(state.get("heading", np.zeros((count, 2))), np.float64).reshape(-1, 2),
        heading_time=np.array([-np.inf if value is None else value for value in heading_time],
                              np.float64).reshape(-1),
        heading_sigma=np.asarray(state.get("heading_sigma", np.zeros(count)),
                                 np.float64).reshape(-1),
        # States saved before these columns: no motion recorded (the next one records it).
        heading_xy=np.array(
            [[np.nan if value is None else value for value in row]
             for row in state.get("heading_xy", [[None, None]] * count)], np.float64,
        ).reshape(-1, 2),
        heading_speed=np.asarray(state.get("heading_speed", np.zeros(count)),
                                 np.float64).reshape(-1),
        seen_covariance=np.asarray(state.get("seen_covariance", covariance[:, :2, :2]),
                                   np.float64).reshape(-1, 2, 2),
        # States saved before the column existed: born when last seen (only the stitching
        # stage reads it, to tell which lost tracks a new track may continue).
        born=None if state.get("born") is None else np.asarray(state["born"],
                                                               np.float64).reshape(-1),
        # States saved before the support stage: nothing counted yet.
        support_seen=_optional(state, "support_seen", cameras),
        support_covered=_optional(state, "support_covered", cameras),
        # States saved before the turning filter: none yet (the next refined view starts it).
        turn_state=None if state.get("turn_state") is None else np.array(
            [[np.nan if value is None else value for value in row]
             for row in state["turn_state"]], np.float64).reshape(-1, 5),
        turn_covariance=None if state.get("turn_covariance") is None else np.asarray(
            state["turn_covariance"], np.float64).reshape(-1, 5, 5),
        turn_time=None if state.get("turn_time") is None else np.array(
            [-np.inf if value is None else value for value in state["turn_time"]],
            np.float64).reshape(-1),
    )
    if len({len(column) for column in tracks.columns()}) != 1:
        raise MatcherError("the saved fusion-tracker state has columns of different lengths.")
    return tracks


def _optional(state: dict, key: str, cameras: int) -> np.ndarray | None:
    """A saved (T, C) column, or None (the table's default) in a state saved without it."""
    value = state.get(key)
    return None if value is None else np.asarray(value, np.float64).reshape(-1, cameras)
