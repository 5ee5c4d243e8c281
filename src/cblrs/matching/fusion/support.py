"""Tracks only one camera ever sees where others look: a detector's persistent false positives.

A real detector fires frame after frame on a sign, a bollard or a reflection. Multi-view
confirmation (``confirm_cameras``) asks a new track for two cameras where two cover its
place, but one coincidence is enough to pass it: a car driving by is seen by a second
camera at the false positive's spot for an instant, or two cameras' false positives meet
within a car's wide gate, and from then on the track is reported for as long as the detector
keeps firing (the roundabout's realistic detector: 40 such tracks, half of all rows
reported). What gives it away is the rest of its life: the other cameras that cover the
spot keep looking at it and never see it.

This stage keeps, per track and camera, the time the camera saw the track and the time it
could have (its view covers the track's place, it sent a message at that instant, and the
track was seen by some camera then: a track missed by every camera says nothing), both
forgotten over ``support_memory_s``. A track is *unsupported* when the cameras other than
the one that sees it most could have seen it for at least ``support_evidence_s``
camera-seconds and saw it for less than ``support_ratio`` of that time, while the camera
that sees it most has seen it for a second at least (a false positive persists; one view
of a person the others happened to miss, at the instant the track starts, is not judged;
many cameras looking at it at 2 fps make two camera-seconds in one instant), and it is not
clearly moving (``confirm_moving_mps`` and three standard deviations of its velocity, as
confirmation has it: a moving object one covering camera cannot see is an occluder the
reference image does not know, a false positive stays where it is). An unsupported track
is neither confirmed nor reported; it stays in the table, so it keeps absorbing its
camera's false detections instead of starting new tracks, and is reported again (its id
kept) as soon as other cameras see it.

Before that judgement, a second confirmation test (:meth:`Support.uncorroborated`): a
tentative track one camera has carried for a second or more (``_LONE_S``: a persistent false
positive waiting for a coincidence) is not confirmed by a second camera's view until the
cameras other than its main one have seen it for at least ``confirm_support_share`` of the
time its main camera did. One instant of a passer-by (a car driving past a sign, 0.1 s
against the sign's second) is not corroboration; a second camera that keeps seeing a person
is. On the realistic detector's 40-car roundabout (seed 1, detector seed 6) 8 of the 35
false-positive ids were confirmed by such a coincidence, after 2 to 7 s as one camera's
tentative track.

A person standing still whom a second covering camera misses for seconds (hidden behind
others) is the price; where one camera alone covers the place nothing changes, and with
exact boxes every covering camera sees every object. ``support_ratio = 0`` turns the stage
off.
"""

from __future__ import annotations

import numpy as np

from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.table import FusionContext, TrackTable

_MAX_STEP_S = 1.0  # longest gap between two instants counted (a stream that paused)
_SEEN_S = 1.0  # a track is judged once one camera has seen it this long (it persists)
_LONE_S = 1.0  # a tentative track this old needs lasting corroboration (uncorroborated)


class Support:
    """Which tracks the cameras covering them do not support (the support stage).

    Args:
        context: the tracker's configuration.
        coverage: where each camera sees the ground.
    """

    def __init__(self, context: FusionContext, coverage: Coverage):
        self.context = context
        self.coverage = coverage
        self.reset()

    def reset(self) -> None:
        """Forget the time of the last instant counted."""
        self._time: float | None = None

    @property
    def enabled(self) -> bool:
        """Whether the stage does anything (``support_ratio > 0``)."""
        return self.context.config.support_ratio > 0

    def learn(
        self,
        tracks: TrackTable,
        seen_now: np.ndarray,
        cameras_of_track: np.ndarray,
        sending: np.ndarray,
        timestamp: float,
    ) -> None:
        """Count this instant: forget old counts, then add the time since the last instant
        to each seen track's cameras that saw it and that could have.

        Args:
            tracks: the tracks as updated at this instant (``support_seen`` and
                ``support_covered`` are updated in place).
            seen_now: (T,) bool, tracks some camera saw now.
            cameras_of_track: (T, C) bool, which cameras saw each track now.
            sending: (K,) indices of the cameras that sent a message at this instant.
            timestamp: the instant, seconds.
        """
        if not self.enabled:
            return
        step = 0.0 if self._time is None else min(max(timestamp - self._time, 0.0), _MAX_STEP_S)
        self._time = timestamp if self._time is None else max(self._time, timestamp)
        if step <= 0 or not len(tracks.ids):
            return
        keep = np.exp(-step / self.context.config.support_memory_s)
        tracks.support_seen *= keep
        tracks.support_covered *= keep
        rows = np.flatnonzero(seen_now)
        if not len(rows):
            return
        covered = self.coverage.covered_by(tracks.state[rows, :2]).T  # (K, C)
        sent = np.zeros(covered.shape[1], dtype=bool)
        sent[np.asarray(sending, np.int64)] = True
        seen = cameras_of_track[rows]
        # A camera that saw the track could see it, whatever its coverage says.
        tracks.support_covered[rows] += step * ((covered & sent[None]) | seen)
        tracks.support_seen[rows] += step * seen

    def unsupported(self, tracks: TrackTable) -> np.ndarray:
        """(T,) bool: tracks the other covering cameras do not see, not clearly moving."""
        result = np.zeros(len(tracks.ids), dtype=bool)
        config = self.context.config
        if not self.enabled or not len(tracks.ids):
            return result
        seen, covered = tracks.support_seen, tracks.support_covered
        rows = np.arange(len(seen))
        best = np.argmax(seen, axis=1)
        other_seen = seen.sum(axis=1) - seen[rows, best]
        other_covered = covered.sum(axis=1) - covered[rows, best]
        result = (
            (seen[rows, best] >= _SEEN_S)
            & (other_covered >= config.support_evidence_s)
            & (other_seen < config.support_ratio * other_covered)
        )
        if config.confirm_moving_mps > 0 and result.any():
            result &= ~tracks.clearly_moving(config.confirm_moving_mps)
        return result

    def uncorroborated(self, tracks: TrackTable, rows: np.ndarray, timestamp: float
                       ) -> np.ndarray:
        """(len(rows),) bool: of the tentative tracks ``rows``, those at least ``_LONE_S``
        old whose cameras other than the main one saw them for less than
        ``confirm_support_share`` of the time the main camera did (see the module notes)."""
        share = self.context.config.confirm_support_share
        result = np.zeros(len(rows), dtype=bool)
        if not self.enabled or share <= 0 or not len(rows):
            return result
        seen = tracks.support_seen[rows]
        main = seen.max(axis=1)
        other = seen.sum(axis=1) - main
        old = timestamp - tracks.born[rows] >= _LONE_S
        return old & (main > 0) & (other < share * main)
