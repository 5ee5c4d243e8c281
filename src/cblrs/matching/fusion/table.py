"""What the fusion tracker's stages share, as explicit values passed to each stage.

* :class:`TrackTable`: one row per track, numpy columns (the tracker owns it; a stage reads
  it, or returns new rows, and never keeps it);
* :class:`FusionContext`: the tracker's constants — configuration, cameras, per-class
  scales — and its learned noise model, given to each stage when it is built;
* :class:`Measured`: per detection of the window being fused, its ray from its camera and
  its noise (the measurement step's output, the association's input).

Every stage (:mod:`~cblrs.matching.fusion.association`, :mod:`~cblrs.matching.fusion.birth`,
:mod:`~cblrs.matching.fusion.clocks`) is a small object built from a context and called by
:class:`~cblrs.matching.fusion.tracker.FusionTracker` with these values, so a test can build
one alone and a new stage is a part one can swap.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.noise import NoiseModel

_FEW_BOXES = 64  # boxes up to which largest_boxes picks in Python
_UNKNOWN_SLOT = np.uint64(len(CLASS_NAMES))  # the per-class arrays' slot of unknown ids


@dataclass
class TrackTable:
    """The tracks, one row each (tentative tracks have id -1).

    Attributes:
        ids: (T,) int64 confirmed ids, -1 while tentative.
        class_id: (T,) int64 class ids.
        state: (T, 4) x, y, vx, vy (m, m/s), the motion models combined.
        covariance: (T, 4, 4) of ``state``.
        mode_state: (T, M, 4) per motion model.
        mode_covariance: (T, M, 4, 4) per motion model.
        mode_probability: (T, M).
        evidence: (T,) int64 detections taken so far.
        last_seen: (T,) seconds.
        seen_by: (T, C) when each camera last saw the track (-inf: never).
        velocity_sigma: (T,) uncertainty of the velocity when last seen, m/s (the root of
            the trace of its covariance; coasting grows the covariance, not this).
        heading: (T, 2) unit direction of motion the last time it was well known (zeros:
            never), for the motion check of vehicles.
        heading_time: (T,) when that was, seconds (-inf: never).
        heading_sigma: (T,) its uncertainty then, radians.
        heading_xy: (T, 2) where the track was then, metres (NaN: never; default).
        heading_speed: (T,) its speed then, m/s (0: never; default).
        seen_covariance: (T, 2, 2) covariance of the position estimated when last seen,
            square metres (default: that of ``covariance`` now).
        born: (T,) when the track was first seen, seconds (for the stitching stage: a new
            track can continue a lost one only if it was born after that one was last
            seen). Defaults to ``last_seen``.
        located: (T, 2) where the track was located at the instant it was last updated,
            when that is sharper than the filter's estimate, metres (NaN: use ``state``;
            default). Only reported, never used to associate
            (:mod:`~cblrs.matching.fusion.vehicle_noise`).
        support_seen: (T, C) time each camera saw the track, recently (seconds, forgotten
            over ``support_memory_s``; the support stage, :mod:`~cblrs.matching.fusion.support`).
        support_covered: (T, C) time each camera could have seen it, the same way.
        turn_state: (T, 5) a vehicle's turning filter, x, y, speed, heading, turn rate
            (m, m, m/s, rad, rad/s; NaN: none yet; default), for the position it is
            reported at (:mod:`~cblrs.matching.fusion.turning`).
        turn_covariance: (T, 5, 5) its covariance (default zeros).
        turn_time: (T,) its time, seconds (-inf: none; default).
    """

    ids: np.ndarray
    class_id: np.ndarray
    state: np.ndarray
    covariance: np.ndarray
    mode_state: np.ndarray
    mode_covariance: np.ndarray
    mode_probability: np.ndarray
    evidence: np.ndarray
    last_seen: np.ndarray
    seen_by: np.ndarray
    velocity_sigma: np.ndarray
    heading: np.ndarray
    heading_time: np.ndarray
    heading_sigma: np.ndarray
    heading_xy: np.ndarray | None = None
    heading_speed: np.ndarray | None = None
    seen_covariance: np.ndarray | None = None
    born: np.ndarray | None = None
    located: np.ndarray | None = None
    support_seen: np.ndarray | None = None
    support_covered: np.ndarray | None = None
    turn_state: np.ndarray | None = None
    turn_covariance: np.ndarray | None = None
    turn_time: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Tables built before these columns existed (births, saved states, tests) start them
        # as never known.
        if self.heading_xy is None:
            self.heading_xy = np.full((len(self.ids), 2), np.nan)
        if self.heading_speed is None:
            self.heading_speed = np.zeros(len(self.ids))
        if self.seen_covariance is None:
            self.seen_covariance = self.covariance[:, :2, :2].copy()
        if self.born is None:
            self.born = np.array(self.last_seen, np.float64, copy=True)
        if self.located is None:
            self.located = np.full((len(self.ids), 2), np.nan)
        if self.support_seen is None:
            self.support_seen = np.zeros(self.seen_by.shape)
        if self.support_covered is None:
            self.support_covered = np.zeros(self.seen_by.shape)
        if self.turn_state is None:
            self.turn_state = np.full((len(self.ids), 5), np.nan)
        if self.turn_covariance is None:
            self.turn_covariance = np.zeros((len(self.ids), 5, 5))
        if self.turn_time is None:
            self.turn_time = np.full(len(self.ids), -np.inf)

    @classmethod
    def empty(cls, models: int, cameras: int) -> TrackTable:
        """No tracks, for ``models`` motion models and ``cameras`` cameras."""
        return cls(
            ids=np.zeros(0, np.int64), class_id=np.zeros(0, np.int64), state=np.zeros((0, 4)),
            covariance=np.zeros((0, 4, 4)), mode_state=np.zeros((0, models, 4)),
            mode_covariance=np.zeros((0, models, 4, 4)),
            mode_probability=np.zeros((0, models)), evidence=np.zeros(0, np.int64),
            last_seen=np.zeros(0), seen_by=np.zeros((0, cameras)), velocity_sigma=np.zeros(0),
            heading=np.zeros((0, 2)), heading_time=np.zeros(0), heading_sigma=np.zeros(0),
            born=np.zeros(0),
        )

    def __len__(self) -> int:
        return len(self.ids)

    def columns(self) -> tuple[np.ndarray, ...]:
        """The columns in declaration order."""
        return (self.ids, self.class_id, self.state, self.covariance, self.mode_state,
                self.mode_covariance, self.mode_probability, self.evidence, self.last_seen,
                self.seen_by, self.velocity_sigma, self.heading, self.heading_time,
                self.heading_sigma, self.heading_xy, self.heading_speed,
                self.seen_covariance, self.born, self.located, self.support_seen,
                self.support_covered, self.turn_state, self.turn_covariance, self.turn_time)

    def clearly_moving(self, min_speed_mps: float, rows: np.ndarray | None = None) -> np.ndarray:
        """Which tracks (of ``rows``; default all) move faster than ``min_speed_mps`` and
        than three standard deviations of their velocity: a bool array, one per row."""
        state = self.state if rows is None else self.state[rows]
        sigma = self.velocity_sigma if rows is None else self.velocity_sigma[rows]
        speed = np.hypot(state[:, 2], state[:, 3])
        return (speed > min_speed_mps) & (speed > 3.0 * sigma)

    def select(self, keep: np.ndarray) -> TrackTable:
        """The rows where ``keep`` (a (T,) mask or indices)."""
        keep = np.asarray(keep)
        if keep.dtype == bool and keep.shape == self.ids.shape and not keep.any():
            # No row (most windows' ended tracks): an empty slice of each column, a sixth of
            # the time of 24 boolean indexings.
            return TrackTable(*(column[:0] for column in self.columns()))
        # Row indices once, then a take per column: a third of the time of a boolean
        # indexing per column (each counts the mask again); the same rows.
        rows = np.flatnonzero(keep) if keep.dtype == bool else keep
        return TrackTable(*(column.take(rows, axis=0) for column in self.columns()))

    def extend(self, other: TrackTable) -> TrackTable:
        """These rows, then ``other``'s (this table itself when ``other`` has none)."""
        if not len(other):
            return self
        return TrackTable(*(np.concatenate([mine, theirs]) for mine, theirs in zip(
            self.columns(), other.columns(), strict=True)))


@dataclass
class Measured:
    """Per detection of the window being fused (N rows), from the measurement step.

    Attributes:
        distance: (N,) metres from the detection's camera (0 where not placed).
        along_distance: (N,) ``distance`` scaled by the camera's height (noise model input).
        direction: (N, 2) unit vectors from the camera to the detection.
        sigma: (N,) the largest standard deviation of each detection, metres.
    """

    distance: np.ndarray
    along_distance: np.ndarray
    direction: np.ndarray
    sigma: np.ndarray

    @classmethod
    def empty(cls) -> Measured:
        """No detections."""
        return cls(np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros(0))


@dataclass
class FusionContext:
    """The tracker's constants and learned noise, shared by its stages.

    Attributes:
        config: the configuration.
        camera_ids: camera names; a camera's index here is its integer id.
        camera_xy: (C, 2) metres, NaN where not placed.
        class_extra: (K + 1,) extra measurement sigma of each class, metres (last: unknown).
        class_scale: (K + 1,) gate and cluster scale relative to a person.
        noise: the learned measurement-noise model.
        class_turn_radius: (K + 1,) smallest turning radius of each class, metres (inf:
            turns on the spot).
        class_velocity_sigma: (K + 1,) how fast an object of each class may be moving when
            its velocity is not known yet, m/s: ``initial_velocity_sigma`` (a person's)
            scaled like the class's acceleration (7.5 m/s for a car). A new track's velocity
            uncertainty, and how far a detection captured a little before or after the
            window's time may have moved per second before its track's velocity compensates it.
    """

    config: FusionConfig
    camera_ids: list[str]
    camera_xy: np.ndarray
    class_extra: np.ndarray
    class_scale: np.ndarray
    noise: NoiseModel
    object_covariance: np.ndarray = field(init=False)
    class_turn_radius: np.ndarray = field(init=False)
    class_velocity_sigma: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.object_covariance = self.config.object_sigma_m**2 * np.eye(2)
        self.class_turn_radius = np.array(
            [self.config.class_turn_radius_m.get(name, np.inf) for name in CLASS_NAMES]
            + [np.inf])
        config = self.config
        acceleration = np.array(
            [config.class_acceleration_sigma.get(name, config.acceleration_sigma)
             for name in CLASS_NAMES] + [config.acceleration_sigma])
        self.class_velocity_sigma = (
            config.initial_velocity_sigma * acceleration / config.acceleration_sigma)

    @property
    def camera_count(self) -> int:
        """Number of cameras C."""
        return len(self.camera_ids)

    @property
    def models(self) -> int:
        """Number of motion models M."""
        return len(self.config.model_sojourn_s)

    @staticmethod
    def class_slot(class_id: np.ndarray) -> np.ndarray:
        """Index into the per-class arrays: the class id, or the last slot for unknown ids."""
        class_id = np.asarray(class_id, np.int64)
        # (A negative id wraps to a huge unsigned one: one minimum clips both ends.)
        return np.minimum(class_id.astype(np.uint64), _UNKNOWN_SLOT).astype(np.int64)


def largest_boxes(
    observed: Observations, matched: np.ndarray, rows: np.ndarray, track_count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Camera and box of each track's largest assigned box (the closest, best view).

    Args:
        observed: the window's detections.
        matched: (N,) bool, the detections that have a track.
        rows: track row of each matched detection.
        track_count: T.

    Returns:
        ``(camera (T,) int64 (-1: none), box (T, 4) pixels (NaN: none))``.
    """
    boxes = observed.xyxy[matched]
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    camera = np.full(track_count, -1, np.int64)
    box = np.full((track_count, 4), np.nan)
    if len(area) <= _FEW_BOXES and not np.isnan(area).any():
        # A window's few boxes in Python: the last of the largest per track, as below.
        largest: dict[int, tuple[float, int]] = {}
        for index, (row, one) in enumerate(zip(rows.tolist(), area.tolist(), strict=True)):
            if row not in largest or one >= largest[row][0]:
                largest[row] = (one, index)
        if largest:
            track = np.fromiter(largest, np.int64, len(largest))
            best = np.fromiter((index for _, index in largest.values()), np.int64,
                               len(largest))
            camera[track] = observed.camera[matched][best]
            box[track] = boxes[best]
        return camera, box
    order = np.lexsort((area, rows))  # by track, then by area ascending
    sorted_rows = rows[order]
    last_of_track = np.append(sorted_rows[1:] != sorted_rows[:-1], True)
    best = order[last_of_track]
    camera[rows[best]] = observed.camera[matched][best]
    box[rows[best]] = boxes[best]
    return camera, box
