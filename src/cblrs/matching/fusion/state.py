"""Snapshots of the fusion tracker: :meth:`Snapshots.get_state` / :meth:`Snapshots.set_state`.

The state is plain JSON-able data, versioned by :data:`STATE_VERSION`; a state saved by a
matcher restores in a new one (the matcher service's autosave).
"""

from __future__ import annotations

import math

import numpy as np

from cblrs.matching.base import (
    MatcherError,
)
from cblrs.matching.fusion.table import TrackTable

STATE_VERSION = "cblrs.fusion-tracker/5"


class Snapshots(TrackTable):
    """Saving and restoring a fusion tracker's state (a mixin of FusionTracker).
    """

    def get_state(self) -> dict:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "version": STATE_VERSION,
            "camera_ids": list(self.camera_ids),
            "time": self._time,
            "next_id": self._next_id,
            "noise": self._noise.get_state(),
            "ids": self._ids.tolist(),
            "class_id": self._class.tolist(),
            "state": self._state.tolist(),
            "covariance": self._covariance.tolist(),
            "evidence": self._evidence.tolist(),
            "last_seen": self._last_seen.tolist(),
            "mode_state": self._mode_state.tolist(),
            "mode_covariance": self._mode_covariance.tolist(),
            "mode_probability": self._mode_probability.tolist(),
            "seen_by": [[value if math.isfinite(value) else None for value in row]
                        for row in self._seen_by.tolist()],
            "windows": self._windows.get_state(),
            "clock": self._clock.get_state(),
            "reported": [[frame, sorted(ids)] for frame, ids in self._reported.items()],
            "clock_turn": self._clock_turn,
        }

    def set_state(self, state: dict) -> None:
        """Restore a state saved by :meth:`get_state`."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise MatcherError(f"not a saved fusion-tracker state (expected {STATE_VERSION}).")
        if state.get("camera_ids") != self.camera_ids:
            raise MatcherError(
                f"the saved state is for cameras {state.get('camera_ids')}, "
                f"this tracker has {self.camera_ids}."
            )
        try:
            time = state["time"]
            self._time = None if time is None else float(time)
            self._next_id = int(state["next_id"])
            self._noise.set_state(state["noise"])
            self._ids = np.asarray(state["ids"], np.int64).reshape(-1)
            self._class = np.asarray(state["class_id"], np.int64).reshape(-1)
            self._state = np.asarray(state["state"], np.float64).reshape(-1, 4)
            self._covariance = np.asarray(state["covariance"], np.float64).reshape(-1, 4, 4)
            self._evidence = np.asarray(state["evidence"], np.int64).reshape(-1)
            self._last_seen = np.asarray(state["last_seen"], np.float64).reshape(-1)
            models = len(self.config.model_sojourn_s)
            self._mode_state = np.asarray(state["mode_state"], np.float64).reshape(
                -1, models, 4)
            self._mode_covariance = np.asarray(state["mode_covariance"], np.float64).reshape(
                -1, models, 4, 4)
            self._mode_probability = np.asarray(
                state["mode_probability"], np.float64).reshape(-1, models)
            self._seen_by = np.array(
                [[-np.inf if value is None else value for value in row]
                 for row in state["seen_by"]], np.float64,
            ).reshape(-1, len(self.camera_ids))
            self._windows.set_state(state["windows"])
            self._clock.set_state(state["clock"])
            self._reported = {int(frame): set(ids) for frame, ids in state["reported"]}
            self._clock_turn = int(state["clock_turn"])
        except (KeyError, TypeError, ValueError, IndexError) as error:
            raise MatcherError(f"the saved fusion-tracker state is incomplete: {error}.") from None
        columns = (self._ids, self._class, self._state, self._covariance, self._evidence,
                   self._last_seen, self._mode_state, self._mode_covariance,
                   self._mode_probability, self._seen_by)
        lengths = {len(column) for column in columns}
        if len(lengths) != 1:
            raise MatcherError("the saved fusion-tracker state has columns of different lengths.")
