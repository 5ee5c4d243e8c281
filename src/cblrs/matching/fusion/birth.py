"""Births and duplicate merging (steps 6 and 7 of the fusion tracker's update).

Detections no track took are clustered across cameras (at most one per camera per cluster,
complete linkage on the Mahalanobis distance) and each cluster starts a tentative track;
confirmed tracks that turn out to be one object are merged (the younger is dropped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cblrs.matching import kalman
from cblrs.matching.base import (
    Observations,
)
from cblrs.matching.fusion.gaussian import (
    close_pairs,
    fuse,
    largest_sigma,
    mahalanobis_squared,
)
from cblrs.matching.fusion.table import FusionContext, TrackTable, largest_boxes
from cblrs.matching.graph import component_labels

_FEW_DETECTIONS = 64  # clusters renumbered in Python up to this many detections


@dataclass
class Born:
    """The tracks a birth step starts, and what the tracker reports of them.

    Attributes:
        tracks: the new rows (tentative, id -1).
        cameras: (B, C) bool, the cameras whose detections started each.
        camera: (B,) int64 camera of each one's largest box.
        box: (B, 4) that box, pixels.
    """

    tracks: TrackTable
    cameras: np.ndarray
    camera: np.ndarray
    box: np.ndarray


class Births:
    """Steps 6 and 7 (births, duplicate merging) of
    :class:`~cblrs.matching.fusion.tracker.FusionTracker`'s update.

    :meth:`birth` returns new rows for the tracker to append; :meth:`merge_duplicates` returns
    a keep-mask over the tracks. Neither changes its inputs.

    Args:
        context: the tracker's configuration, cameras and per-class scales.
    """

    def __init__(self, context: FusionContext):
        self.context = context

    def birth(self, leftovers: Observations, covariance: np.ndarray, timestamp: float) -> Born:
        """Start a tentative track per cross-camera cluster of unassigned detections."""
        if not len(leftovers):  # (most windows: every detection has a track)
            return Born(TrackTable.empty(self.context.models, self.context.camera_count),
                        np.zeros((0, self.context.camera_count), dtype=bool),
                        np.zeros(0, np.int64), np.zeros((0, 4)))
        sigma = largest_sigma(covariance)
        labels = cluster_detections(
            leftovers.world_xy, leftovers.camera, sigma,
            self.context.config.cluster_sigmas, leftovers.class_id,
            self.context.config.cluster_radius_m
            * self.context.class_scale[self.context.class_slot(leftovers.class_id)],
            covariance=covariance,
        )
        count = int(labels.max()) + 1 if len(labels) else 0
        camera_count = self.context.camera_count
        cameras = np.zeros((count, camera_count), dtype=bool)
        if count == 0:
            return Born(TrackTable.empty(self.context.models, camera_count), cameras,
                        np.full(count, -1, np.int64), np.full((count, 4), np.nan))
        position, position_covariance, _ = fuse(
            labels, count, leftovers.world_xy, covariance
        )
        state = np.zeros((count, 4))
        state[:, :2] = position
        cluster_class = np.zeros(count, np.int64)
        cluster_class[labels] = leftovers.class_id  # one class per cluster
        # A new track's velocity is unknown: up to a walking pace for a person, a driving
        # one for a car (FusionContext.class_velocity_sigma). Started at a person's
        # uncertainty, a car's track would lag its views for a second.
        covariance = kalman.initial_covariance(
            count, position_covariance + self.context.object_covariance,
            self.context.class_velocity_sigma[self.context.class_slot(cluster_class)],
        )
        cameras[labels, leftovers.camera] = True
        camera, box = largest_boxes(leftovers, np.ones(len(labels), dtype=bool), labels, count)
        models = self.context.models
        config = self.context.config
        born = TrackTable(
            ids=np.full(count, -1, np.int64),
            class_id=cluster_class,
            state=state,
            covariance=covariance,
            mode_state=np.repeat(state[:, None], models, axis=1),
            mode_covariance=np.repeat(covariance[:, None], models, axis=1),
            mode_probability=np.tile(
                kalman.stationary_probability(np.asarray(config.model_sojourn_s)), (count, 1)),
            evidence=np.bincount(labels, minlength=count),
            last_seen=np.full(count, timestamp),
            seen_by=np.where(cameras, timestamp, -np.inf),
            velocity_sigma=np.sqrt(covariance[:, 2, 2] + covariance[:, 3, 3]),
            heading=np.zeros((count, 2)),
            heading_time=np.full(count, -np.inf),
            heading_sigma=np.zeros(count),
            born=np.full(count, timestamp),
        )
        return Born(born, cameras, camera, box)

    def merge_duplicates(
        self, tracks: TrackTable, seen_now: np.ndarray, cameras_of_track: np.ndarray
    ) -> np.ndarray:
        """Keep-mask dropping the younger of two confirmed tracks that are one object."""
        keep = np.ones(len(tracks.ids), dtype=bool)
        if self.context.config.merge_radius_m <= 0:
            return keep
        candidates = np.flatnonzero(seen_now & (tracks.ids >= 0))
        if len(candidates) < 2:
            return keep
        position = tracks.state[candidates, :2]
        first, second = close_pairs(
            position, position, np.full(len(candidates), self.context.config.merge_radius_m),
            strict=True,
        )
        upper = first < second
        first, second = candidates[first[upper]], candidates[second[upper]]
        disjoint = ~(cameras_of_track[first] & cameras_of_track[second]).any(axis=1)
        for one, other in zip(first[disjoint].tolist(), second[disjoint].tolist(), strict=True):
            if keep[one] and keep[other]:
                younger = one if tracks.ids[one] > tracks.ids[other] else other
                keep[younger] = False
        return keep


def cluster_detections(
    world_xy: np.ndarray,
    camera: np.ndarray,
    sigma_m: float | np.ndarray,
    sigmas: float,
    class_id: np.ndarray | None = None,
    minimum_radius_m: float | np.ndarray = 0.0,
    covariance: np.ndarray | None = None,
) -> np.ndarray:
    """Group same-instant detections of several cameras into objects.

    Complete-linkage agglomeration over pairs closer than ``sigmas`` standard deviations of
    their difference (closest first), with
    at most one detection per camera and one class in a cluster (a camera sees an object
    once).

    Args:
        world_xy: (N, 2) float64 metres.
        camera: (N,) int64 camera index of each detection.
        sigma_m: position noise of each detection, metres, scalar or (N,).
        sigmas: a pair is compatible within ``sigmas * sqrt(sigma_1**2 + sigma_2**2)``.
        class_id: (N,) int64 classes; None treats all detections as one class.
        minimum_radius_m: a pair is always compatible within this distance, metres, scalar
            or (N,) (a pair uses the larger of its two).
        covariance: optional (N, 2, 2) position covariances, square metres; then a pair is
            compatible within ``sigmas`` in the Mahalanobis metric of the sum of its two
            covariances (``sigma_m`` should then be the largest standard deviation of each,
            for the neighbour search), and pairs merge in order of that metric.

    Returns:
        (N,) int64 cluster labels 0..K-1, numbered by first member.
    """
    count = len(world_xy)
    if count == 0:
        return np.zeros(0, np.int64)
    variance = np.broadcast_to(np.asarray(sigma_m, np.float64) ** 2, (count,))
    minimum = np.broadcast_to(np.asarray(minimum_radius_m, np.float64), (count,))
    # Candidate pairs: a sparse neighbour search with the largest radius, then each pair's own.
    largest = np.maximum(sigmas * np.sqrt(variance + variance.max()), minimum.max())
    first, second = close_pairs(world_xy, world_xy, largest)
    upper = first < second
    first, second = first[upper], second[upper]
    difference = world_xy[first] - world_xy[second]
    distance = np.linalg.norm(difference, axis=1)
    pair_minimum = np.maximum(minimum[first], minimum[second])
    if covariance is None:
        radius = np.maximum(sigmas * np.sqrt(variance[first] + variance[second]), pair_minimum)
        keep = distance <= radius
    else:
        normalised = np.sqrt(
            mahalanobis_squared(difference, covariance[first] + covariance[second])
        )
        keep = (normalised <= sigmas) | (distance <= pair_minimum)
        # Merge order: the most likely pairs first.
        distance = np.minimum(normalised, sigmas * distance / np.maximum(pair_minimum, 1e-9))
    keep &= camera[first] != camera[second]
    if class_id is not None:
        keep &= class_id[first] == class_id[second]
    first, second, distance = first[keep], second[keep], distance[keep]

    # Components of the compatibility graph. A component that is a clique with one
    # detection per camera is one cluster (the greedy merge below would join it whole);
    # only the other components need the greedy complete-linkage merge.
    component = component_labels(count, first, second)
    size = np.bincount(component)
    edges = np.bincount(component[first], minlength=len(size))
    camera_slots = int(camera.max()) + 1
    has_camera = np.zeros(len(size) * camera_slots, dtype=bool)
    has_camera[component * camera_slots + camera] = True
    cameras_in = has_camera.reshape(len(size), camera_slots).sum(axis=1)
    clean = (edges == size * (size - 1) // 2) & (cameras_in == size)
    label = component.copy()
    bad = np.flatnonzero(~clean)
    if len(bad):
        by_detection = np.argsort(component, kind="stable")
        detection_start = np.searchsorted(component[by_detection], bad)
        pair_component = component[first]
        by_pair = np.argsort(pair_component, kind="stable")
        pair_start = np.searchsorted(pair_component[by_pair], bad)
        next_label = count
        for index, one in enumerate(bad.tolist()):
            members = by_detection[detection_start[index]:detection_start[index] + size[one]]
            pairs = by_pair[pair_start[index]:pair_start[index] + edges[one]]
            local = _greedy_complete_linkage(
                members, first[pairs], second[pairs], distance[pairs], camera
            )
            label[members] = next_label + local
            next_label += len(members)
    # Renumber by first appearance so labels are stable and deterministic.
    if count <= _FEW_DETECTIONS:  # (in Python: the same numbers, fewer numpy calls)
        number: dict[int, int] = {}
        return np.array([number.setdefault(one, len(number)) for one in label.tolist()],
                        np.int64)
    _, first_index, inverse = np.unique(label, return_index=True, return_inverse=True)
    rank = np.empty(len(first_index), np.int64)
    rank[np.argsort(first_index, kind="stable")] = np.arange(len(first_index))
    return rank[inverse.reshape(-1)]


def _greedy_complete_linkage(
    members: np.ndarray, first: np.ndarray, second: np.ndarray, distance: np.ndarray,
    camera: np.ndarray,
) -> np.ndarray:
    """Closest-first merging of one component's detections; complete linkage, one per camera.

    Args:
        members: (M,) detection indices of the component.
        first, second, distance: its compatible pairs (global indices) and their distances.
        camera: (N,) camera of every detection.

    Returns:
        (M,) local cluster labels in 0..M-1 (not necessarily consecutive), in the order of
        ``np.sort(members)``.
    """
    members = np.sort(members)
    left_local = np.searchsorted(members, first).tolist()
    right_local = np.searchsorted(members, second).tolist()
    # Sets as Python integers, one bit per member (or per camera): a merge test is then a
    # few integer operations however large the clusters grow.
    compatible = [0] * len(members)  # bit j of member i: i and j may share a cluster
    for left, right in zip(left_local, right_local, strict=True):
        compatible[left] |= 1 << right
        compatible[right] |= 1 << left
    label = list(range(len(members)))
    groups: list[list[int]] = [[local] for local in range(len(members))]
    member_bits = [1 << local for local in range(len(members))]
    camera_bits = [1 << int(one) for one in camera[members].tolist()]
    # Cluster g may take member j when bit j is set: j is compatible with all of g.
    joinable = compatible.copy()
    for pair in np.argsort(distance, kind="stable").tolist():
        left, right = label[left_local[pair]], label[right_local[pair]]
        if left == right or camera_bits[left] & camera_bits[right]:
            continue
        if member_bits[right] & ~joinable[left]:
            continue
        for local in groups[right]:
            label[local] = left
        groups[left].extend(groups[right])
        groups[right] = []
        member_bits[left] |= member_bits[right]
        camera_bits[left] |= camera_bits[right]
        joinable[left] &= joinable[right]
    return np.asarray(label, dtype=np.int64)
