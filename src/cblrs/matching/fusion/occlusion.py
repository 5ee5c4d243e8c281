"""Tracks hidden behind someone: missed by every camera, each for a reason (the hidden stage).

A confirmed track that no camera detected at an instant is either gone (it left, or was a
false positive) or hidden: in a crowd a person walking right behind another is covered in
every view that could see them, often for a second or more, while the ground truth, and
whoever counts people, still has them. The tracker keeps coasting such a track for
``max_age_s`` anyway; this stage decides whether to *report* it meanwhile.

A missed track is hidden at an instant when every camera whose view covers its predicted
position (:class:`~cblrs.matching.fusion.coverage.Coverage`) has a detection in front of it
that a track took: nearer to the camera, and within a body's width of the track's bearing
from the camera (the nearer box covers the farther one in that image). A camera that covers
the place and sees nothing there, or sees only things beside or behind it, would have seen
the person: the track is not reported. A track whose position no camera covers is not
reported either (leaving the located area is not being hidden).

Whether cameras miss people who are hidden at all depends on the boxes: a detector does,
annotated boxes (WILDTRACK's) do not, and there a person missed by every camera has left.
The stage learns it online, from the people seen at each instant: of their views that a
nearer detection hides, the share their camera missed; only above one half are hidden
tracks reported. Only people (vehicles are left to their own stages).

Needs the cameras' ground positions (``camera_positions``); without them nothing is reported
hidden.
"""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES, CLASS_SIZE_PRIORS
from cblrs.matching.base import Observations
from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.low_confidence import take_measured
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable

PERSON_HEIGHT_M = CLASS_SIZE_PRIORS["person"][2]
_COVERED = 0.75  # share of a box a nearer one must cover to hide it
_PERSON = CLASS_NAMES.index("person")
_PRIOR_VIEWS = 20.0
_SETTLED_VIEWS = 2000.0


class Hidden:
    """Which missed confirmed tracks are hidden behind nearer detections in every view.

    Args:
        context: the tracker's configuration and cameras (``camera_xy``).
        coverage: where each camera sees the ground.
    """

    def __init__(self, context: FusionContext, coverage: Coverage):
        self.context = context
        self.coverage = coverage
        # Farthest a hidden person may be, as a multiple of the occluder's distance, per
        # camera: from a camera above head height a farther person's head shows above a
        # nearer one's, so the nearer covers most of the farther only close in front of it.
        self.depth_ratio = np.full(context.camera_count, np.inf)
        positions = context.config.camera_positions or {}
        height = PERSON_HEIGHT_M
        for camera, name in enumerate(context.camera_ids):
            position = positions.get(name)
            if position is not None and len(position) == 3 and position[2] > height:
                self.depth_ratio[camera] = (position[2] - (1.0 - _COVERED) * height) / (
                    position[2] - height)
        self.reset()

    def reset(self) -> None:
        """Forget the learnt miss rate of occluded views."""
        self.occluded_views = 0.0
        self.occluded_missed = 0.0
        self._turn = 0

    @property
    def miss_rate(self) -> float:
        """Share of the occluded views of seen people that their camera missed, learnt so far
        (with a prior of ``_PRIOR_VIEWS`` views detected: a few misses early on do not
        turn the stage on)."""
        return self.occluded_missed / (self.occluded_views + _PRIOR_VIEWS)

    def get_state(self) -> dict:
        """What has been learnt, JSON-ready."""
        return {"views": self.occluded_views, "missed": self.occluded_missed}

    def set_state(self, state: dict | None) -> None:
        """Restore :meth:`get_state`'s data (None: nothing learnt)."""
        self.reset()
        if state is not None:
            self.occluded_views = float(state["views"])
            self.occluded_missed = float(state["missed"])

    def learn(
        self, tracks: TrackTable, seen_now: np.ndarray, observed: Observations,
        measured: Measured, assigned: np.ndarray,
    ) -> None:
        """Count, over the people seen at this instant, the views where a nearer detection
        hides them and whether their camera detected them anyway.

        Args:
            tracks: the tracks as updated at this instant.
            seen_now: (T,) bool, the tracks some camera saw now.
            observed, measured: the window's detections and their distances.
            assigned: (N,) track row of each detection (-1: none).
        """
        if self.context.config.report_hidden_s <= 0:
            return
        # Once thousands of views are counted the rate is known: then one instant in ten
        # keeps it current at a tenth of the cost.
        self._turn += 1
        if self.occluded_views >= _SETTLED_VIEWS and self._turn % 10:
            return
        # Only a placed camera can find a view hidden (see _occluded).
        placed = np.isfinite(self.context.camera_xy).all(axis=1)
        if self.context.config.occluder_width_m <= 0 or not placed.any():
            return
        rows = np.flatnonzero(seen_now & (tracks.ids >= 0) & (tracks.class_id == _PERSON))
        if len(rows) == 0:
            return
        position = tracks.state[rows, :2]
        covering = self.coverage.covered_by(position)
        of_camera = _by_camera(observed.camera, self.context.camera_count)
        for camera in np.flatnonzero(covering.any(axis=1) & placed).tolist():
            testing = np.flatnonzero(covering[camera])
            mine = of_camera[camera]
            if len(mine) == 0:
                continue
            occluded = self._occluded(camera, position[testing], observed, measured, mine,
                                      rows[testing], assigned)
            if not occluded.any():
                continue
            detected = np.zeros(len(tracks.ids), dtype=bool)
            detected[assigned[mine][assigned[mine] >= 0]] = True
            self.occluded_views += float(occluded.sum())
            self.occluded_missed += float((~detected[rows[testing][occluded]]).sum())

    def missed(
        self, tracks: TrackTable, report: np.ndarray, timestamp: float,
        observed: Observations, measured: Measured, matched: np.ndarray | None = None,
    ) -> np.ndarray:
        """(T,) bool: the confirmed tracks not in ``report`` (missed now), missed for at most
        ``report_hidden_s`` and hidden at this instant (:meth:`hidden`) behind detections
        that tracks took (``matched``, (N,) bool; None: any detection)."""
        limit = self.context.config.report_hidden_s
        candidates = ~report & (tracks.ids >= 0) & (timestamp - tracks.last_seen <= limit)
        if limit <= 0 or not candidates.any():
            return np.zeros(len(tracks.ids), dtype=bool)
        if matched is not None:
            observed, measured = observed[matched], take_measured(measured, matched)
        return self.hidden(tracks, candidates, observed, measured)

    def hidden(
        self, tracks: TrackTable, candidates: np.ndarray, observed: Observations,
        measured: Measured,
    ) -> np.ndarray:
        """(T,) bool: the ``candidates`` (a (T,) mask of missed tracks) hidden at this instant.

        Only people, and only once the cameras are known to miss most of the views a nearer
        detection hides (:attr:`miss_rate` above one half): where they detect people through
        occlusion (annotated boxes), a person missed by every camera has left.

        Args:
            tracks: the tracks, predicted to the window's time.
            candidates: (T,) bool, the tracks to test.
            observed: the window's detections (positions and cameras).
            measured: their distances from their cameras (``measured.distance``).
        """
        result = np.zeros(len(tracks.ids), dtype=bool)
        rows = np.flatnonzero(candidates & (tracks.class_id == _PERSON))
        if len(rows) == 0 or self.miss_rate <= 0.5:
            return result
        position = tracks.state[rows, :2]
        covering = self.coverage.covered_by(position)  # (C, K)
        hidden = covering.any(axis=0)
        of_camera = _by_camera(observed.camera, self.context.camera_count)
        for camera in np.flatnonzero(covering.any(axis=1)).tolist():
            testing = covering[camera] & hidden
            if not testing.any():
                continue
            mine = of_camera[camera]
            if len(mine) == 0:
                hidden &= ~covering[camera]
                continue
            occluded = self._occluded(camera, position[testing], observed, measured, mine)
            hidden[np.flatnonzero(testing)[~occluded]] = False
        result[rows] = hidden
        return result

    def _occluded(
        self, camera: int, position: np.ndarray, observed: Observations, measured: Measured,
        mine: np.ndarray, rows: np.ndarray | None = None, assigned: np.ndarray | None = None,
    ) -> np.ndarray:
        """(K,) bool: each position has one of the camera's detections ``mine`` in front of
        it (a detection assigned to the position's own track row, if given, does not count).
        """
        width = self.context.config.occluder_width_m
        camera_xy = self.context.camera_xy[camera]
        if width <= 0 or not np.isfinite(camera_xy).all():
            return np.zeros(len(position), dtype=bool)
        offset = position - camera_xy
        distance = np.hypot(offset[:, 0], offset[:, 1])
        bearing = offset / np.maximum(distance, 1e-9)[:, None]
        front = observed.world_xy[mine] - camera_xy
        front_distance = measured.distance[mine]
        # How far each detection lies beside the line of sight to the position: within a
        # body's width (half of each body), its box overlaps the position's across. Nearer
        # (not behind it, up to the depth ratio the camera's height allows), it covers it
        # along too.
        cross = np.abs(bearing[:, None, 0] * front[None, :, 1]
                       - bearing[:, None, 1] * front[None, :, 0])
        along = np.einsum("kj,nj->kn", bearing, front)
        covered = (cross <= width) & (along > 0) & (
            front_distance[None, :] < distance[:, None] + 0.5 * width) & (
            distance[:, None] <= self.depth_ratio[camera] * front_distance[None, :]
            + 0.5 * width)
        if rows is not None and assigned is not None:
            covered &= assigned[mine][None, :] != rows[:, None]
        return covered.any(axis=1)


def _by_camera(camera: np.ndarray, camera_count: int) -> list[np.ndarray]:
    """The indices of each camera's detections, in one pass: (N,) camera index -> C arrays."""
    order = np.argsort(camera, kind="stable")
    bounds = np.searchsorted(camera[order], np.arange(camera_count + 1))
    return [order[bounds[one]:bounds[one + 1]] for one in range(camera_count)]
