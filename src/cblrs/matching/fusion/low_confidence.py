"""Low-confidence detections, confirmed by a live track or another camera (steps 3 and 4c).

A detector run at a modest threshold (0.25) both misses people it sees weakly (far, half
hidden) and fires on things that are not people (a bag, a shadow, a second box around one
person) with scores just as low. One camera cannot tell them apart; the tracker can: a weak
box where a track is and other cameras see it too, or where a second camera is sure of
somebody, is a person; a weak box seen by one camera where other cameras look and see
nobody is weak evidence. This is ByteTrack's idea (Zhang et al., ECCV 2022: associate the
high-scoring boxes first, let the low-scoring ones extend the tracks, never start one)
made multi-view. Scores at or above ``high_confidence``
(:data:`~cblrs.detections.SURE_CONFIDENCE`, 0.5) are high:

1. high-confidence detections are associated with the tracks as usual (the association
   stage, :mod:`~cblrs.matching.fusion.association`);
2. then the low-confidence ones, each track taking at most one detection per camera: a
   camera that gave the track a high-confidence box this instant gives it nothing more,
   so a weak duplicate box never displaces the sure one;
3. leftovers of either kind join a track other cameras saw at this instant when they are
   consistent with its fused position (the association stage's own step 4);
4. a track keeps its low-confidence detections of this instant only when the instant is
   multi-view evidence for it: a high-confidence detection too, or low-confidence ones
   from two cameras, or a place fewer than two cameras see (the reference images say
   where each camera sees the ground, :mod:`~cblrs.matching.fusion.coverage`; there no
   second view can confirm anything). Otherwise they are dropped and the track coasts;
5. an unassigned low-confidence detection is kept only when it clusters with an
   unassigned high-confidence detection of another camera (the birth stage's clustering,
   so the views that confirm each other are the views that start one track together:
   a second camera for the new track at once), or with weak ones of two other cameras
   (:data:`WEAK_VIEWS_TO_START`: three cameras each seeing somebody weakly at one place
   is no one camera's mistake; it is a person hidden in every view, or a multi-view
   detector whose boxes all carry the score of one ground-plane detection). Alone, or
   with one other camera's weak box, it is dropped: two cameras' weak boxes of one place
   were, on the real detector's MultiviewX boxes, mostly a thing both take for a person
   (docs/real-frames.md).

Dropped detections reach neither the filters, the noise model, the clocks nor the births.
High-confidence detections are treated exactly as without this stage, so boxes that carry
no score (annotations, confidence 1) track as before.
"""

from __future__ import annotations

import numpy as np

from cblrs.matching.base import Observations
from cblrs.matching.fusion.association import Association
from cblrs.matching.fusion.birth import cluster_detections
from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.gaussian import largest_sigma
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable

WEAK_VIEWS_TO_START = 3
"""Cameras whose low-confidence detections of one place start a track without a sure one."""


class LowConfidence:
    """Two-stage association by detector score, and which detections the tracker keeps.

    Inputs: the tracks predicted to the window's time, the window's detections (positions,
    covariances, scores) and their :class:`Measured` rays; outputs: each detection's track
    row (:meth:`associate`) and the detections to keep (:meth:`kept`). It changes neither
    the tracks nor its inputs.

    Args:
        context: the tracker's configuration (``high_confidence``, the clustering radii).
        association: the association stage both passes run.
        coverage: where each camera sees the ground (the tracker's).
    """

    def __init__(self, context: FusionContext, association: Association, coverage: Coverage):
        self.context = context
        self.association = association
        self.coverage = coverage

    def is_high(self, observed: Observations) -> np.ndarray:
        """(N,) bool: detections scoring at least ``high_confidence``."""
        return observed.confidence >= self.context.config.high_confidence

    def associate(
        self,
        tracks: TrackTable,
        measured: Measured,
        observed: Observations,
        covariance: np.ndarray,
        timestamp: float | None = None,
    ) -> np.ndarray:
        """Track row of each detection (-1: none): high-confidence detections first, then the
        low-confidence ones against what the first pass left, then leftovers join tracks
        seen at this instant (steps 1-3 of the module notes). ``timestamp``: as for
        :meth:`Association.associate`."""
        high = self.is_high(observed)
        association = self.association
        if high.all() or len(tracks.ids) == 0:
            # Nothing to hold back: the association stage alone (identical results for
            # boxes without scores).
            assigned = association.associate(tracks, measured, observed, covariance, timestamp)
            return association.join_observed(
                tracks, measured, observed, covariance, assigned, timestamp
            )
        assigned = np.full(len(observed), -1, np.int64)
        strong = np.flatnonzero(high)
        if len(strong):
            assigned[strong] = association.associate(
                tracks,
                take_measured(measured, strong),
                observed[strong],
                covariance[strong],
                timestamp,
            )
        weak = np.flatnonzero(~high)
        weak_track = association.associate(
            tracks, take_measured(measured, weak), observed[weak], covariance[weak], timestamp
        )
        # A camera that already gave the track a strong box gives it nothing more.
        taken = np.zeros((len(tracks.ids), self.context.camera_count), dtype=bool)
        matched = assigned >= 0
        taken[assigned[matched], observed.camera[matched]] = True
        ok = weak_track >= 0
        ok[ok] = ~taken[weak_track[ok], observed.camera[weak[ok]]]
        assigned[weak[ok]] = weak_track[ok]
        return association.join_observed(
            tracks, measured, observed, covariance, assigned, timestamp
        )

    def kept(
        self,
        tracks: TrackTable,
        observed: Observations,
        covariance: np.ndarray,
        assigned: np.ndarray,
    ) -> np.ndarray:
        """(N,) bool: the detections the tracker keeps (steps 4 and 5 of the module notes).

        Every high-confidence one; a low-confidence one assigned to a track when the
        track's views of this instant are multi-view evidence (or no second camera sees
        its place); an unassigned low-confidence one when it clusters with an unassigned
        high-confidence detection of another camera, or with unassigned detections of
        ``WEAK_VIEWS_TO_START - 1`` other cameras.
        """
        high = self.is_high(observed)
        keep = high.copy()
        if keep.all():
            return keep
        matched = assigned >= 0
        weak = matched & ~high
        if weak.any():
            keep[weak] = self._track_confirms(tracks, observed, assigned, high)[assigned[weak]]
        leftover = np.flatnonzero(~matched)
        if len(leftover) and not high[leftover].all():
            class_id = observed.class_id[leftover]
            labels = cluster_detections(
                observed.world_xy[leftover],
                observed.camera[leftover],
                largest_sigma(covariance[leftover]),
                self.context.config.cluster_sigmas,
                class_id,
                self.context.config.cluster_radius_m
                * self.context.class_scale[self.context.class_slot(class_id)],
                covariance=covariance[leftover],
            )
            # A cluster holds at most one detection per camera: a high-confidence member
            # is another camera's sure view of the same place.
            sure = np.bincount(labels, high[leftover].astype(np.float64)) > 0
            seen_weakly = np.bincount(labels) >= WEAK_VIEWS_TO_START
            keep[leftover] |= (sure | seen_weakly)[labels]
        return keep

    def _track_confirms(
        self, tracks: TrackTable, observed: Observations, assigned: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        """(T,) bool: tracks whose low-confidence views of this instant they may keep."""
        count = len(tracks.ids)
        matched = assigned >= 0
        strong = np.zeros(count, dtype=bool)
        strong[assigned[matched & high]] = True
        weak = matched & ~high
        cameras = np.zeros((count, self.context.camera_count), dtype=bool)
        cameras[assigned[weak], observed.camera[weak]] = True
        lone = ~strong & (cameras.sum(axis=1) == 1)
        if not lone.any():
            return np.ones(count, dtype=bool)
        # One camera's weak view alone counts where no second camera sees the ground.
        confirms = ~lone
        rows = np.flatnonzero(lone)
        confirms[rows] = self.coverage.covering(tracks.state[rows, :2]) < 2
        return confirms


def take_measured(measured: Measured, index: np.ndarray) -> Measured:
    """The rays and noise of the detections at ``index``."""
    return Measured(
        measured.distance[index],
        measured.along_distance[index],
        measured.direction[index],
        measured.sigma[index],
    )
