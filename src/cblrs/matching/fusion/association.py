"""Association of detections to tracks (steps 3 and 4 of the fusion tracker's update).

Groups of precise detections are assigned across cameras as one observation; the rest camera
by camera, most precise first, then in the reverse order where tracks compete, keeping the
more likely assignment of each contested group. Leftovers then join a track other cameras saw
at this instant when they are consistent with its fused position. Given the window's time, a
pair whose detection a vehicle track cannot have reached (outside its reachable cone,
:mod:`cblrs.matching.fusion.reachable`: a car does not reverse or jump across the road) is
not gated at all, so the assignment looks for that detection's own track. To try another
association, change this module: :meth:`Association.associate` and
:meth:`Association.join_observed` are what the tracker calls.
"""

from __future__ import annotations

import numpy as np

from cblrs.arrays import median_of_few, unique_integers
from cblrs.matching import kalman
from cblrs.matching.base import (
    Observations,
)
from cblrs.matching.fusion.birth import cluster_detections
from cblrs.matching.fusion.gaussian import (
    close_pairs,
    fuse,
    largest_sigma,
    mahalanobis_squared,
)
from cblrs.matching.fusion.reachable import ReachableCone
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable
from cblrs.matching.graph import component_labels
from cblrs.matching.solvers import linear_sum_assignment

_UNASSIGNABLE = 1.0e9


class Association:
    """Steps 3 and 4 of :class:`~cblrs.matching.fusion.tracker.FusionTracker`'s update.

    Inputs: the tracks predicted to the window's time, the window's detections (positions and
    covariances) and their :class:`Measured` rays; output: each detection's track row (-1:
    none). It changes neither the tracks nor its inputs.

    Args:
        context: the tracker's configuration, cameras and noise model.
    """

    def __init__(self, context: FusionContext):
        self.context = context
        self.cone = ReachableCone(context)

    def associate(
        self, tracks: TrackTable, measured: Measured, observed: Observations,
        covariance: np.ndarray, timestamp: float | None = None,
    ) -> np.ndarray:
        """Track row of each detection (-1: none); one detection per camera per track.

        ``timestamp`` (the window's time, seconds) turns on the reachable-cone gate of
        vehicle tracks; None gates by position alone.
        """
        return _Run(self.context, tracks, measured, timestamp, self.cone)._associate(
            observed, covariance)

    def join_observed(
        self, tracks: TrackTable, measured: Measured, observed: Observations,
        covariance: np.ndarray, assigned: np.ndarray, timestamp: float | None = None,
    ) -> np.ndarray:
        """``assigned`` with leftovers joined to tracks other cameras saw at this instant
        (``timestamp`` as in :meth:`associate`)."""
        return _Run(self.context, tracks, measured, timestamp, self.cone)._join_observed(
            observed, covariance, assigned)

    def joint_cost(
        self, tracks: TrackTable, measured: Measured, observed: Observations,
        covariance: np.ndarray, assigned: np.ndarray, order: list[int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Negative log-likelihood of an assignment: (T,) per track, (N,) per unassigned
        detection (see :meth:`_Run._joint_cost`)."""
        return _Run(self.context, tracks, measured)._joint_cost(observed, covariance,
                                                                  assigned, order)


class _Run:
    """One association: the stage's inputs held for its steps, which call each other."""

    def __init__(
        self, context: FusionContext, tracks: TrackTable, measured: Measured,
        timestamp: float | None = None, cone: ReachableCone | None = None,
    ):
        self.context = context
        self.tracks = tracks
        self.measured = measured
        self.timestamp = timestamp
        self.cone = cone if cone is not None else ReachableCone(context)
        self._limits: tuple[np.ndarray, ...] | None = None  # computed at the first gate
        self._turning: bool | None = None  # some track has a reachable cone (first gate)

    def _reachable(self, columns: np.ndarray, xy: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """(K,) bool: each position lies within its vehicle track's reachable cone (all True
        without a timestamp)."""
        if self.timestamp is None:
            return np.ones(len(columns), dtype=bool)
        if self._turning is None:  # only a class with a turning radius has a cone
            context = self.context
            self._turning = bool(np.isfinite(
                context.class_turn_radius[context.class_slot(self.tracks.class_id)]).any())
        if not self._turning:
            return np.ones(len(columns), dtype=bool)
        if self._limits is None:
            self._limits = self.cone.limits(self.tracks, self.timestamp)
        return self.cone.feasible(self.tracks, self.timestamp, columns, xy, covariance,
                                  self._limits)

    def _associate(self, observed: Observations, covariance: np.ndarray) -> np.ndarray:
        """Track row of each detection (-1: none); one detection per camera per track.

        Precise detections are first grouped across cameras and each group is assigned to a
        track as a whole (:meth:`_associate_groups`): when two people walk side by side,
        cameras deciding one by one could each pick differently and blend them. The rest
        is assigned camera by camera.
        """
        count, track_count = len(observed), len(self.tracks.ids)
        if count == 0 or track_count == 0:
            return np.full(count, -1, np.int64)
        assigned = self._associate_groups(observed, covariance)
        rest = np.flatnonzero(assigned < 0)
        if len(rest) == 0:
            return assigned
        taken = np.zeros((track_count, self.context.camera_count), dtype=bool)
        taken[assigned[assigned >= 0], observed.camera[assigned >= 0]] = True
        # A detection whose gate component holds one track and at most one detection per
        # camera is assigned alike in every camera order: it takes that track directly (if
        # more likely than leaving it unassigned), and only contested detections go through
        # the camera-by-camera assignment below. (One camera has a single order anyway.)
        contested = np.ones(len(rest), dtype=bool)
        rest_cameras = observed.camera[rest]
        if (rest_cameras != rest_cameras[0]).any():  # more than one camera
            contested, rows, columns, cost = self._contested(observed, covariance, rest)
            direct = ~contested[rows]
            if direct.any():
                detection, columns, cost = rest[rows[direct]], columns[direct], cost[direct]
                camera = observed.camera[detection]
                ok = (cost <= self._unassigned_cost(covariance[detection])) & ~taken[
                    columns, camera]
                assigned = assigned.copy()
                assigned[detection[ok]] = columns[ok]
                taken[columns[ok], camera[ok]] = True
            # Gate components leave whole, so every detection still to assign is contested.
            rest = rest[contested]
            contested = contested[contested]
            if len(rest) == 0:
                return assigned
        rest_camera = observed.camera[rest]
        cameras = unique_integers(rest_camera)
        precision = np.array([median_of_few(self.measured.sigma[rest[rest_camera == one]])
                              for one in cameras.tolist()])
        order = cameras[np.argsort(precision, kind="stable")].tolist()
        best = self._associate_in_order(observed, covariance, assigned, rest, taken, order)
        if self.context.config.association_orders > 1 and len(order) > 1:
            # The camera order is a heuristic and an early wrong choice propagates to the
            # cameras after it. Assign again in other orders (the reverse first, then
            # rotations) and keep, in each group of tracks and detections where the
            # assignments differ, the one that explains them more likely.
            orders = [order[::-1]] + [order[k:] + order[:k] for k in range(1, len(order))]
            orders = orders[: self.context.config.association_orders - 1] if contested.any() else []
            if orders:
                # Uncontested detections keep their track; only the others are reassigned.
                settled = rest[~contested & (best[rest] >= 0)]
                others_taken = taken.copy()
                others_taken[best[settled], observed.camera[settled]] = True
                start = assigned.copy()
                start[settled] = best[settled]
                best_track, best_detection = self._joint_cost(observed, covariance, best, order)
            for index, other_order in enumerate(orders):
                candidate = self._associate_in_order(
                    observed, covariance, start, rest[contested], others_taken, other_order
                )
                differ = np.flatnonzero(candidate != best)
                if len(differ) == 0:
                    continue
                track_cost, detection_cost = self._joint_cost(
                    observed, covariance, candidate, order
                )
                best = _merge_assignments(
                    best, candidate, differ, best_track, best_detection, track_cost,
                    detection_cost,
                )
                if index + 1 < len(orders):
                    best_track, best_detection = self._joint_cost(
                        observed, covariance, best, order
                    )
        return best

    def _contested(
        self, observed: Observations, covariance: np.ndarray, rest: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Which detections ``rest`` could be assigned differently in another camera order.

        Connected components of the gate graph (detections and tracks linked by the pairs
        within the gate of the prediction) with one track and at most one detection per
        camera are settled; every other component is contested.

        Returns:
            ``(contested (R,) bool, rows, columns, cost)``: the mask and the gated pairs
            (positions in ``rest``, track rows, costs) of :meth:`_gated_pairs`.
        """
        rows, columns, cost = self._gated_pairs(
            observed.world_xy[rest], covariance[rest], observed.class_id[rest]
        )
        contested = np.zeros(len(rest), dtype=bool)
        if len(rows) == 0:
            return contested, rows, columns, cost
        track_count = len(self.tracks.ids)
        node_count = len(rest) + track_count
        label = component_labels(node_count, rows, len(rest) + columns)
        size = int(label.max()) + 1
        tracks_in = np.bincount(label[len(rest):], minlength=size)
        detection_label = label[: len(rest)]
        camera_count = self.context.camera_count
        per_camera = np.bincount(
            detection_label * camera_count + observed.camera[rest],
            minlength=size * camera_count,
        ).reshape(size, camera_count)
        busy = (tracks_in > 1) | (per_camera.max(axis=1) > 1)
        return busy[detection_label], rows, columns, cost

    def _joint_cost(
        self, observed: Observations, covariance: np.ndarray, assigned: np.ndarray,
        order: list[int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Negative log-likelihood of an assignment, split into (T,) per track (its cameras'
        innovations in turn) and (N,) per unassigned detection (as if at the gate)."""
        state, state_covariance = self.tracks.state.copy(), self.tracks.covariance.copy()
        track_count = len(self.tracks.ids)
        unassigned = assigned < 0
        spare = covariance + self.context.object_covariance
        detection_cost = np.where(
            unassigned,
            self.context.config.gate_sigmas**2
            + np.log(spare[:, 0, 0] * spare[:, 1, 1] - spare[:, 0, 1] * spare[:, 1, 0]),
            0.0,
        )
        track_cost = np.zeros(track_count)
        for one in order:
            mine = np.flatnonzero((observed.camera == one) & ~unassigned)
            if len(mine) == 0:
                continue
            tracks = assigned[mine]
            innovation = (state_covariance[tracks, :2, :2] + covariance[mine]
                          + self.context.object_covariance)
            determinant = (innovation[:, 0, 0] * innovation[:, 1, 1]
                           - innovation[:, 0, 1] * innovation[:, 1, 0])
            track_cost += np.bincount(
                tracks,
                mahalanobis_squared(observed.world_xy[mine] - state[tracks, :2], innovation)
                + np.log(determinant),
                minlength=track_count,
            )
            state[tracks], state_covariance[tracks] = kalman.update(
                state[tracks], state_covariance[tracks], observed.world_xy[mine],
                covariance[mine],
            )
        return track_cost, detection_cost

    def _associate_in_order(
        self, observed: Observations, covariance: np.ndarray, assigned: np.ndarray,
        rest: np.ndarray, taken: np.ndarray, order: list[int],
    ) -> np.ndarray:
        """Camera-by-camera assignment of the detections ``rest`` in the given camera order."""
        assigned = assigned.copy()
        track_count = len(self.tracks.ids)
        rest_camera = observed.camera[rest]
        # Cameras are processed one after the other, as a Kalman filter processes
        # independent sensors: each camera's detections are assigned against the tracks
        # as already corrected by the cameras before it, most precise camera first. A
        # camera that sees two people side by side along its ray cannot tell them apart,
        # but one looking across that ray can, and its correction is then used.
        state, state_covariance = self.tracks.state, self.tracks.covariance
        grouped = assigned >= 0
        if grouped.any():
            state, state_covariance = state.copy(), state_covariance.copy()
            position, fused_covariance, present = fuse(
                assigned[grouped], track_count, observed.world_xy[grouped],
                covariance[grouped],
            )
            state[present], state_covariance[present] = kalman.update(
                state[present], state_covariance[present], position[present],
                fused_covariance[present],
            )
        for one in order:
            mine = rest[rest_camera == one]
            rows, columns, cost = self._gated_pairs(
                observed.world_xy[mine], covariance[mine], observed.class_id[mine],
                state, state_covariance,
            )
            free = ~taken[columns, one]
            chosen = assign_per_camera(
                rows[free], columns[free], cost[free], np.zeros(len(mine), np.int64), 1,
                self._unassigned_cost(covariance[mine]),
            )
            assigned[mine] = chosen
            ok = chosen >= 0
            if ok.any():
                if state is self.tracks.state:
                    state, state_covariance = state.copy(), state_covariance.copy()
                tracks = chosen[ok]
                state[tracks], state_covariance[tracks] = kalman.update(
                    state[tracks], state_covariance[tracks], observed.world_xy[mine[ok]],
                    covariance[mine[ok]],
                )
        for _ in range(self.context.config.refine_passes if len(order) > 1 else 0):
            for one in order:
                # Revisit each camera against the tracks corrected by all other cameras.
                others = (assigned >= 0) & (observed.camera != one)
                position, fused_covariance, present = fuse(
                    assigned[others], track_count, observed.world_xy[others], covariance[others]
                )
                state, state_covariance = self.tracks.state.copy(), self.tracks.covariance.copy()
                state[present], state_covariance[present] = kalman.update(
                    state[present], state_covariance[present], position[present],
                    fused_covariance[present],
                )
                mine = rest[rest_camera == one]
                rows, columns, cost = self._gated_pairs(
                    observed.world_xy[mine], covariance[mine], observed.class_id[mine],
                    state, state_covariance,
                )
                free = ~taken[columns, one]
                assigned[mine] = assign_per_camera(
                    rows[free], columns[free], cost[free], np.zeros(len(mine), np.int64), 1,
                    self._unassigned_cost(covariance[mine]),
                )
        return assigned

    def _unassigned_cost(self, covariance: np.ndarray) -> np.ndarray:
        """(N,) cost of leaving each detection unassigned: that of one at the gate.

        With it the camera's assignment is the most likely one rather than the one with
        the most pairs: when a track's own detection was missed, a neighbour's detection
        near the edge of its gate is left to its own object instead of being forced onto
        the track. It is the cost :meth:`_joint_cost` charges an unassigned detection.
        """
        spare = covariance + self.context.object_covariance
        return self.context.config.gate_sigmas**2 + np.log(
            spare[:, 0, 0] * spare[:, 1, 1] - spare[:, 0, 1] * spare[:, 1, 0]
        )

    def _gated_pairs(
        self, world_xy: np.ndarray, covariance: np.ndarray, class_id: np.ndarray,
        state: np.ndarray | None = None, state_covariance: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gated (measurement, track) pairs and their negative log-likelihood costs.

        ``state`` and ``state_covariance`` ((T, 4), (T, 4, 4)) default to the tracks'
        predictions.

        The metric cap grows with the class's size (vehicles) and with the detection's own
        noise (``gate_sigmas`` of its largest standard deviation), not with the track's: an
        uncertain (coasting) track must not reach across a crowd. Only pairs within it are
        evaluated further, so the cost grows with the pairs, not N x T.
        """
        context = self.context
        cap = context.config.max_gate_m * context.class_scale[context.class_slot(class_id)]
        # A detection reaches as far as its own noise along its ray allows (a far view is
        # metres uncertain along the ray); the Mahalanobis gate still bounds it across.
        cap = np.maximum(cap, self.context.config.gate_sigmas * largest_sigma(covariance))
        state = self.tracks.state if state is None else state
        state_covariance = self.tracks.covariance if state_covariance is None else state_covariance
        rows, columns = close_pairs(world_xy, state[:, :2], cap)
        rows, columns = _same_class(rows, columns, class_id, self.tracks.class_id)
        innovation = (state_covariance[columns, :2, :2] + covariance[rows]
                      + self.context.object_covariance)
        determinant = (innovation[:, 0, 0] * innovation[:, 1, 1]
                       - innovation[:, 0, 1] * innovation[:, 1, 0])
        mahalanobis = mahalanobis_squared(world_xy[rows] - state[columns, :2], innovation)
        inside = mahalanobis <= self.context.config.gate_sigmas**2
        if inside.any():
            inside[inside] = self._reachable(columns[inside], world_xy[rows[inside]],
                                             covariance[rows[inside]])
        # Negative log-likelihood of the innovation (constant dropped).
        cost = mahalanobis[inside] + np.log(determinant[inside])
        return rows[inside], columns[inside], cost

    def _associate_groups(self, observed: Observations, covariance: np.ndarray) -> np.ndarray:
        """Assign cross-camera groups of precise detections to tracks, one group per track.

        A detection is precise when its cluster radius under the learned noise model
        (``cluster_sigmas * sqrt(2) * sigma``) is within ``group_radius_m``. Groups of two
        or more such detections (one per camera, complete linkage) are fused and assigned
        to tracks with one Hungarian assignment.
        """
        assigned = np.full(len(observed), -1, np.int64)
        if self.context.config.group_radius_m <= 0:
            return assigned
        slot = self.context.class_slot(observed.class_id)
        sigma = np.sqrt(
            self.context.noise.variance(self.measured.distance, self.measured.along_distance)
            + self.context.class_extra[slot] ** 2)
        limit = self.context.config.group_radius_m * self.context.class_scale[slot]
        precise = np.flatnonzero(self.context.config.cluster_sigmas * np.sqrt(2.0) * sigma <= limit)
        if len(precise) < 2:
            return assigned
        labels = cluster_detections(
            observed.world_xy[precise], observed.camera[precise], self.measured.sigma[precise],
            self.context.config.cluster_sigmas, observed.class_id[precise],
            covariance=covariance[precise],
        )
        size = np.bincount(labels)
        grouped = size[labels] >= 2
        if not grouped.any():
            return assigned
        members, labels = precise[grouped], labels[grouped]
        used = np.zeros(int(labels.max()) + 1, dtype=bool)  # labels renumbered 0..G-1
        used[labels] = True
        labels = (np.cumsum(used) - 1)[labels]
        group_count = int(labels.max()) + 1
        position, group_covariance, _ = fuse(
            labels, group_count, observed.world_xy[members], covariance[members]
        )
        group_class = np.zeros(group_count, np.int64)
        group_class[labels] = observed.class_id[members]
        rows, columns, cost = self._gated_pairs(position, group_covariance, group_class)
        # Groups compete for tracks as if they all came from one camera: one-to-one.
        group_track = assign_per_camera(
            rows, columns, cost, np.zeros(group_count, np.int64), 1
        )
        assigned[members] = group_track[labels]
        return assigned

    def _join_observed(
        self, observed: Observations, covariance: np.ndarray, assigned: np.ndarray
    ) -> np.ndarray:
        """Let detections the gate missed join a track other cameras saw at this instant.

        The gate is a boundary in the prediction's frame; when it cuts through the views of
        one object (a sudden turn), some cameras take the track and the rest would start a
        duplicate. Leftovers within the cluster radius of a track's fused position this
        instant, from a camera that gave the track nothing, join it instead.
        """
        matched = assigned >= 0
        leftover = np.flatnonzero(~matched)
        if len(leftover) == 0 or not matched.any():
            return assigned
        track_count = len(self.tracks.ids)
        tracks = assigned[matched]
        fused, fused_covariance, present = fuse(
            tracks, track_count, observed.world_xy[matched], covariance[matched]
        )
        seen = np.flatnonzero(present)
        fused, fused_covariance = fused[seen], fused_covariance[seen]
        taken = np.zeros((track_count, self.context.camera_count), dtype=bool)
        taken[tracks, observed.camera[matched]] = True

        slots = self.context.class_slot(observed.class_id[leftover])
        floor = self.context.config.cluster_radius_m * self.context.class_scale[slots]
        fused_largest = float(np.max(fused_covariance[:, 0, 0] + fused_covariance[:, 1, 1]))
        largest = np.maximum(
            floor,
            self.context.config.cluster_sigmas
            * np.sqrt(self.measured.sigma[leftover] ** 2 + fused_largest),
        )
        rows, columns = close_pairs(observed.world_xy[leftover], fused, largest)
        rows, columns = _same_class(rows, columns, observed.class_id[leftover],
                                    self.tracks.class_id[seen])
        difference = observed.world_xy[leftover[rows]] - fused[columns]
        distance = np.linalg.norm(difference, axis=1)
        normalised = np.sqrt(mahalanobis_squared(
            difference, covariance[leftover[rows]] + fused_covariance[columns]
        ))
        allowed = (
            (normalised <= self.context.config.cluster_sigmas) | (distance <= floor[rows])
        ) & ~taken[seen[columns], observed.camera[leftover[rows]]]
        if allowed.any():
            allowed[allowed] = self._reachable(
                seen[columns[allowed]], observed.world_xy[leftover[rows[allowed]]],
                covariance[leftover[rows[allowed]]])
        joined = assign_per_camera(
            rows[allowed], columns[allowed], normalised[allowed], observed.camera[leftover],
            self.context.camera_count,
        )
        assigned = assigned.copy()
        ok = joined >= 0
        assigned[leftover[ok]] = seen[joined[ok]]
        return assigned


def _same_class(
    rows: np.ndarray, columns: np.ndarray, row_class: np.ndarray, column_class: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    keep = row_class[rows] == column_class[columns]
    return rows[keep], columns[keep]


def assign_per_camera(
    rows: np.ndarray, columns: np.ndarray, cost: np.ndarray, camera: np.ndarray,
    camera_count: int, unassigned_cost: np.ndarray | None = None,
) -> np.ndarray:
    """Hungarian assignment of detections to tracks, solved per camera, on allowed pairs.

    Each camera assigns its detections independently: a track takes at most one detection
    of each camera, a detection goes to at most one track, only the given pairs are allowed
    and the sum of costs is minimal among assignments with the most pairs.

    Args:
        rows: (K,) int64 detection index of each allowed pair.
        columns: (K,) int64 track index of each allowed pair.
        cost: (K,) float64 cost of each pair.
        camera: (N,) int64 camera index of every detection (N detections).
        camera_count: number of cameras C.

    Returns:
        (N,) int64 track index of each detection, -1 for none.
    """
    count = len(camera)
    assigned = np.full(count, -1, np.int64)
    if len(rows) == 0:
        return assigned
    # A pair alone in its row and alone in its (track, camera) column is its own component
    # of the assignment graph: taking it is what the Hungarian would do. Only the contested
    # pairs go to the solver, camera by camera.
    column_key = columns * camera_count + camera[rows]
    per_row = np.bincount(rows, minlength=count)
    trivial = (per_row[rows] == 1) & (np.bincount(column_key)[column_key] == 1)
    if unassigned_cost is not None:
        taken = trivial & (cost <= unassigned_cost[rows])
    else:
        taken = trivial
    assigned[rows[taken]] = columns[taken]
    contested = ~trivial & (per_row[rows] > 0)
    if not contested.any():
        return assigned
    rows, columns, cost = rows[contested], columns[contested], cost[contested]
    pair_camera = camera[rows]
    for one_camera in unique_integers(pair_camera).tolist():
        mine = pair_camera == one_camera
        block_rows, row_index = np.unique(rows[mine], return_inverse=True)
        block_columns, column_index = np.unique(columns[mine], return_inverse=True)
        width = len(block_columns)
        if unassigned_cost is not None:
            width += len(block_rows)
        block = np.full((len(block_rows), width), _UNASSIGNABLE)
        block[row_index, column_index] = cost[mine]
        if unassigned_cost is not None:
            spare = np.arange(len(block_rows))
            block[spare, len(block_columns) + spare] = unassigned_cost[block_rows]
        chosen_rows, chosen_columns = linear_sum_assignment(block)
        valid = (block[chosen_rows, chosen_columns] < _UNASSIGNABLE) & (
            chosen_columns < len(block_columns))
        assigned[block_rows[chosen_rows[valid]]] = block_columns[chosen_columns[valid]]
    return assigned


def _merge_assignments(
    best: np.ndarray, candidate: np.ndarray, differ: np.ndarray, best_track: np.ndarray,
    best_detection: np.ndarray, candidate_track: np.ndarray, candidate_detection: np.ndarray,
) -> np.ndarray:
    """Combine two assignments, taking the cheaper one in each group where they differ.

    A group is a connected set of tracks and detections linked by the detections assigned
    differently (a detection links the track it has in either assignment); groups share no
    track and no detection, so any choice per group is a valid assignment.

    Args:
        best, candidate: (N,) int64 track of each detection (-1: none).
        differ: (D,) indices of the detections where they differ.
        best_track, candidate_track: (T,) cost of each track under either assignment.
        best_detection, candidate_detection: (N,) cost of each detection left unassigned.

    Returns:
        (N,) int64 the combined assignment.
    """
    if len(differ) == 0:
        return best.copy()
    track_count = len(best_track)
    node_count = track_count + len(best)
    source = np.concatenate([differ + track_count, differ + track_count])
    target = np.concatenate([best[differ], candidate[differ]])
    keep = target >= 0
    label = component_labels(node_count, source[keep], target[keep])
    track_label, detection_label = label[:track_count], label[track_count:]
    involved = unique_integers(detection_label[differ])
    size = int(label.max()) + 1
    track_gain = np.bincount(track_label, best_track - candidate_track, minlength=size)
    detection_gain = np.bincount(
        detection_label, best_detection - candidate_detection, minlength=size
    )
    better = np.zeros(size, dtype=bool)
    better[involved] = (track_gain + detection_gain)[involved] > 1e-9
    merged = best.copy()
    take = differ[better[detection_label[differ]]]
    merged[take] = candidate[take]
    return merged
