"""The fusion tracker: one observation per object per instant, Kalman-tracked on the ground.

Where the paper's matcher compares every detection with every object, camera by camera,
this tracker uses what the colour code makes possible: every camera's detections land in
the same metric ground frame, so the views of one person at one instant are noisy
observations of one point. Per instant:

1. decode all colours to world positions (metres); give each detection a covariance
   elongated along the ray from its camera (a box edge's pixel error moves a foot point
   along the viewing direction far more than across it) and remove the learned along-ray
   bias;
2. predict every track to the instant with an interacting multiple-model filter: two
   constant-velocity Kalman filters, one steady and one manoeuvring (white-noise
   accelerations of a quarter of and twice the class's: a person walking straight
   hardly accelerates, one turning or stopping does), weighed
   by how well each has been predicting;
3. associate: groups of precise detections are assigned across cameras as one observation;
   the rest camera by camera, most precise camera first, each against the tracks as
   corrected by the cameras before it (as a Kalman filter processes independent sensors),
   then once more against the tracks corrected by all other cameras. Each step is a
   Hungarian assignment on the negative log-likelihood, gated by Mahalanobis distance,
   a metric cap and class (a track takes at most one detection from each camera). An
   early wrong choice propagates to the cameras after it, so where tracks compete the
   cameras are assigned again in the reverse order, and each connected group of tracks
   and detections where the two assignments differ keeps the more likely one (the sum of
   the cameras' innovation costs, an unassigned detection costing as much as one at the
   gate);
4. let leftovers join a track other cameras saw at this instant when they are consistent
   with its fused position (the gate must not split one object's views);
5. fuse each track's detections in information form (inverse covariances) and update the
   filter once, adding an object-level noise common to all views;
6. cluster the remaining detections across cameras (at most one per camera per cluster,
   complete linkage on the Mahalanobis distance) and start a tentative track per cluster;
7. confirm tracks with enough evidence (camera detections), optionally merge duplicates,
   delete tracks unseen for too long.

Cameras need not be synchronised. Messages are fused in windows of nearby capture times
(:mod:`cblrs.matching.timing`: a fraction of the shortest frame period wide, one message per
camera, released once no camera can still add to it), each detection at its own capture time:
its gate is widened by how far its class moves in its lag to the window's latest time, and
once it has a track it is moved along the track's velocity to that time before fusion. Each
camera's clock offset is estimated from the data and subtracted from its timestamps
(:mod:`cblrs.matching.clock`): finely from how its views lead or trail the other cameras'
views of the same walking people, coarsely (seconds: a wrong clock) by searching the lag at
which its views land on the other cameras' tracks. A window is reported at the capture time
of each frame it holds, one row per confirmed track and frame.

Measurement noise is ``a**2 + (b * d)**2`` along the ray and ``e**2 + (c * d)**2`` across
it (``d`` the distance from the camera, along the ray scaled by the camera's height when
known), and :class:`NoiseModel` re-estimates the four coefficients and a bias online from
how much the cameras that see one object disagree, so the same defaults serve exact boxes
and a noisy detector. All parameters are physical (metres, seconds, m/s, m/s^2): the same
defaults serve 2 fps datasets and 10 or 20 fps video. Everything is online; there is no
look-ahead.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment, nnls
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.matching import kalman
from cblrs.matching.base import (
    MatcherError,
    Observations,
    build_config,
    camera_index,
    decode_messages,
    require,
)
from cblrs.matching.clock import DEFAULT_MAX_OFFSET_S, DEFAULT_TOLERANCE_S, ClockModel
from cblrs.matching.timing import (
    DEFAULT_MAX_WINDOW_S,
    DEFAULT_WINDOW_FRACTION,
    Window,
    WindowBuffer,
)
from cblrs.plane import PlaneSet

logger = logging.getLogger(__name__)

STATE_VERSION = "cblrs.fusion-tracker/5"
_REPORTED_FRAMES = 64  # frames remembered to report each track at most once per frame
_CORROBORATION_S = 2.0  # a track seen by another camera this recently corroborates a view
_UNASSIGNABLE = 1.0e9
_DENSE_PAIRS = 20_000  # below this many N x T pairs a dense distance matrix is faster


# Vehicles are located less precisely than people (their footprint is metres long and the
# box bottom only bounds it) and turn harder; everything else falls back to the base values.
DEFAULT_CLASS_MEASUREMENT_SIGMA_M: dict[str, float] = {
    "car": 0.7, "truck": 1.0, "bus": 1.2, "bicycle": 0.3, "motorcycle": 0.4,
}
DEFAULT_CLASS_ACCELERATION_SIGMA: dict[str, float] = {
    "car": 5.0, "truck": 2.0, "bus": 2.0, "bicycle": 1.5, "motorcycle": 3.0,
}


def _positive(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and (
        math.isfinite(value) and value > 0
    )


@dataclass(frozen=True)
class FusionConfig:
    """Options of the fusion tracker, all in physical units.

    Attributes:
        measurement_sigma_m: initial standard deviation of one camera's ground position of
            an object, metres, independent of distance (the prior of the noise model).
        sigma_per_distance: initial standard deviation across the ray per metre of distance
            between camera and object (needs ``camera_positions``): a pixel error covers
            more ground far away. Dimensionless; learned when ``adapt_noise`` (see
            :class:`NoiseModel`).
        along_sigma_per_distance: the same along the ray, per metre of distance scaled by
            the camera's height (a box bottom off by ``e`` of the box height moves a
            person's foot point by about ``e x 1.75 m x distance / camera height``).
            The default, about 4 % of the box height, is on the loose side on purpose:
            the online model shrinks a too-large noise to the cameras' agreement within a
            few instants, but grows a too-small one only slowly (residuals beyond three
            standard deviations of the current model are clipped), and meanwhile it
            splits one person's views into several tracks.
        minimum_sigma_m: smallest standard deviation of one camera's ground position, however
            closely the cameras agree, metres.
        object_sigma_m: standard deviation of an object's position common to all the views
            of one instant, metres: a person is not a point (where the views' foot points
            fall on the body, where the ground truth marks it) and does not move at exactly
            constant velocity. Cameras' disagreement cannot reveal it, so it is added once to
            each instant's fused observation rather than to every camera's.
        adapt_noise: re-estimate the noise model and the along-ray bias online from the
            disagreement of the cameras that see the same object at the same instant (so the
            same defaults serve exact boxes and a noisy detector); False keeps the initial
            values.
        class_measurement_sigma_m: extra standard deviation (added in quadrature) for classes
            whose footprint is large (vehicles: the box bottom only bounds it), metres;
            the gate cap and the cluster radius grow with it.
        camera_positions: optional ``{camera_id: (x, y)}`` or ``{camera_id: (x, y, height)}``
            positions of the cameras, metres; without them the measurement noise does not
            depend on distance nor direction. With heights for every camera, the along-ray
            noise grows with ``distance / height`` (a box edge's pixel error moves the foot
            point along the ground by ``~ object height x distance / camera height`` per
            unit of relative box error), scaled to the cameras' mean height.
        acceleration_sigma: white-noise acceleration of a person's motion model, m/s^2.
        class_acceleration_sigma: the same for other classes, ``{class name: m/s^2}``.
        model_acceleration_factors: the motion model is an interacting multiple-model
            filter: constant-velocity models whose white-noise accelerations are these
            multiples of the class's (people mostly walk steadily, sometimes turn or stop:
            0.25 m/s^2 and 2 m/s^2 for a person); ``(1.0,)`` is a single constant-velocity
            filter.
        model_sojourn_s: mean time spent in each of those models, seconds (one per model).
        initial_velocity_sigma: velocity uncertainty of a new track, m/s.
        gate_sigmas: Mahalanobis gate on the innovation (standard deviations).
        max_gate_m: cap on the distance between a track and a detection it takes, metres
            (larger for a detection whose own noise is larger: ``gate_sigmas`` times its
            largest standard deviation).
        cluster_sigmas: two cameras' detections can be one object when their distance is
            within this many standard deviations of their difference,
            ``sqrt(sigma_1**2 + sigma_2**2)``, or within ``cluster_radius_m``.
        cluster_radius_m: smallest such radius for people (two views of one person land
            apart by body size and calibration error however precise the boxes); grows with
            the class's size for vehicles.
        group_radius_m: detections precise enough that their cluster radius under the
            learned noise is within this are first grouped across cameras and assigned as
            one observation per object, metres (0: always assign camera by camera).
        refine_passes: after the cameras are assigned one after the other, each camera's
            detections are assigned again this many times against the tracks as corrected
            by all the other cameras (0: one sequential pass only).
        association_orders: camera orders the sequential assignment is run in (the most
            precise camera first, then the reverse, then rotations); where the assignments
            differ, each connected group of tracks and detections keeps the one with the
            smaller negative log-likelihood (1: the most-precise-first order only).
        merge_radius_m: two confirmed tracks closer than this, observed at the same instant
            by disjoint sets of cameras, are one object seen twice; the younger one is dropped.
        confirm_evidence: camera detections (summed over instants) a track needs before it
            is reported.
        tentative_max_age_s: a tentative track unseen this long is dropped, seconds.
        max_age_s: a confirmed track unseen this long is dropped, seconds.
        report_coasting_s: keep reporting the prediction of a confirmed track that was
            missed for at most this long, seconds (0: report only observed tracks).
        max_window_s: messages are fused in windows of nearby capture times (see
            :mod:`cblrs.matching.timing`), at most this wide, seconds.
        window_fraction: window width as a fraction of the shortest camera frame period.
        max_lag_s: a message whose corrected capture time is older than the tracker's time
            by more than this cannot be fused any more and is dropped (counted), seconds.
        estimate_clocks: estimate each camera's clock offset from the data and correct its
            timestamps (see :mod:`cblrs.matching.clock`); False trusts the timestamps.
        clock_tolerance_s: a camera whose clock is estimated off by more than this is
            reported (logged, and in :meth:`FusionTracker.clock_report`), seconds.
        max_clock_offset_s: largest clock error searched for when a camera's locations stop
            matching the other cameras' tracks, seconds (0: only the fine estimate).
    """

    measurement_sigma_m: float = 0.2
    sigma_per_distance: float = 0.01
    along_sigma_per_distance: float = 0.03
    minimum_sigma_m: float = 0.05
    object_sigma_m: float = 0.1
    adapt_noise: bool = True
    class_measurement_sigma_m: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_MEASUREMENT_SIGMA_M)
    )
    camera_positions: Mapping[str, Sequence[float]] | None = None
    acceleration_sigma: float = 1.0
    class_acceleration_sigma: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_ACCELERATION_SIGMA)
    )
    model_acceleration_factors: tuple[float, ...] = (0.25, 2.0)
    model_sojourn_s: tuple[float, ...] = (10.0, 2.0)
    initial_velocity_sigma: float = 1.5
    gate_sigmas: float = 4.0
    max_gate_m: float = 2.0
    cluster_sigmas: float = 3.5
    cluster_radius_m: float = 1.0
    group_radius_m: float = 0.7
    refine_passes: int = 1
    association_orders: int = 2
    merge_radius_m: float = 0.0
    confirm_evidence: int = 2
    tentative_max_age_s: float = 1.0
    max_age_s: float = 2.0
    report_coasting_s: float = 0.0
    max_window_s: float = DEFAULT_MAX_WINDOW_S
    window_fraction: float = DEFAULT_WINDOW_FRACTION
    max_lag_s: float = 0.5
    estimate_clocks: bool = True
    clock_tolerance_s: float = DEFAULT_TOLERANCE_S
    max_clock_offset_s: float = DEFAULT_MAX_OFFSET_S

    def __post_init__(self) -> None:
        for name in (
            "measurement_sigma_m", "minimum_sigma_m", "acceleration_sigma",
            "initial_velocity_sigma", "gate_sigmas", "max_gate_m", "cluster_sigmas",
            "cluster_radius_m", "tentative_max_age_s", "max_age_s", "max_window_s",
            "window_fraction", "max_lag_s", "clock_tolerance_s",
        ):
            value = getattr(self, name)
            require(_positive(value), f"{name} must be a positive number, got {value!r}.")
        for name in ("sigma_per_distance", "along_sigma_per_distance", "merge_radius_m",
                     "report_coasting_s", "object_sigma_m", "group_radius_m",
                     "max_clock_offset_s"):
            value = getattr(self, name)
            require(
                _positive(value) or value == 0,
                f"{name} must be zero or a positive number, got {value!r}.",
            )
        for name in ("model_acceleration_factors", "model_sojourn_s"):
            values = getattr(self, name)
            require(
                isinstance(values, Sequence) and not isinstance(values, str) and len(values) > 0
                and all(_positive(value) for value in values),
                f"{name} must be a non-empty list of positive numbers, got {values!r}.",
            )
            object.__setattr__(self, name, tuple(float(value) for value in values))
        require(
            len(self.model_acceleration_factors) == len(self.model_sojourn_s),
            "model_acceleration_factors and model_sojourn_s need one entry per model, got "
            f"{len(self.model_acceleration_factors)} and {len(self.model_sojourn_s)}.",
        )
        for name in ("adapt_noise", "estimate_clocks"):
            value = getattr(self, name)
            require(isinstance(value, bool), f"{name} must be true or false, got {value!r}.")
        require(
            self.window_fraction < 1,
            f"window_fraction must be below 1 (a fraction of a frame period), "
            f"got {self.window_fraction!r}.",
        )
        require(
            isinstance(self.refine_passes, int) and not isinstance(self.refine_passes, bool)
            and self.refine_passes >= 0,
            f"refine_passes must be a whole number >= 0, got {self.refine_passes!r}.",
        )
        require(
            isinstance(self.association_orders, int)
            and not isinstance(self.association_orders, bool) and self.association_orders >= 1,
            f"association_orders must be a whole number >= 1, got {self.association_orders!r}.",
        )
        require(
            isinstance(self.confirm_evidence, int) and not isinstance(self.confirm_evidence, bool)
            and self.confirm_evidence >= 1,
            f"confirm_evidence must be a whole number >= 1, got {self.confirm_evidence!r}.",
        )
        for name in ("class_measurement_sigma_m", "class_acceleration_sigma"):
            table = getattr(self, name)
            require(isinstance(table, Mapping), f"{name} must map class names to numbers.")
            for class_name, value in table.items():
                require(
                    class_name in CLASS_NAMES,
                    f"{name}: unknown class {class_name!r}; known: {', '.join(CLASS_NAMES)}.",
                )
                require(
                    _positive(value),
                    f"{name}[{class_name!r}] must be a positive number, got {value!r}.",
                )
            object.__setattr__(self, name, {str(k): float(v) for k, v in table.items()})
        if self.camera_positions is not None:
            require(
                isinstance(self.camera_positions, Mapping),
                "camera_positions must map camera ids to (x, y) metres.",
            )
            positions: dict[str, tuple[float, ...]] = {}
            for name, position in self.camera_positions.items():
                point = np.asarray(position, dtype=np.float64).reshape(-1)
                require(
                    len(point) in (2, 3) and bool(np.isfinite(point).all()),
                    f"camera position of {name!r} must be finite (x, y) or (x, y, height) "
                    f"metres, got {position!r}.",
                )
                if len(point) == 3:
                    require(
                        point[2] > 0,
                        f"camera height of {name!r} must be above the ground, "
                        f"got {point[2]:g} m.",
                    )
                positions[str(name)] = tuple(float(value) for value in point)
            object.__setattr__(self, "camera_positions", positions)


class FusionTracker:
    """Multi-camera fusion tracker (the default matcher).

    Args:
        planes: the planes the cameras' colours refer to.
        camera_ids: names of the cameras; a camera's index here is ``Tracks.camera_id``.
        **options: fields of :class:`FusionConfig`.

    Example:
        >>> from cblrs.plane import PlaneSet, PlaneSpec
        >>> tracker = FusionTracker(PlaneSet([PlaneSpec(1, (0, 0), 10, 10)]), ["a", "b"])
        >>> len(tracker.update(0.0, []))
        0
    """

    name = "fusion"

    def __init__(self, planes: PlaneSet, camera_ids: Sequence[str], **options: Any):
        self.config = build_config(FusionConfig, options, self.name)
        self.planes = planes if isinstance(planes, PlaneSet) else PlaneSet(planes)
        self.camera_ids = [str(name) for name in camera_ids]
        self._cameras = camera_index(self.camera_ids)
        self._camera_xy = np.full((len(self.camera_ids), 2), np.nan)
        # Along-ray distances are scaled by mean height / camera height when all placed
        # cameras have a height (1 otherwise).
        self._along_scale = np.ones(len(self.camera_ids))
        if self.config.camera_positions is not None:
            unknown = sorted(set(self.config.camera_positions) - set(self.camera_ids))
            require(not unknown, f"camera_positions names unknown camera(s): {unknown}.")
            heights = {}
            for name, position in self.config.camera_positions.items():
                self._camera_xy[self._cameras[name]] = position[:2]
                if len(position) == 3:
                    heights[self._cameras[name]] = position[2]
            if heights and len(heights) == len(self.config.camera_positions):
                index = np.array(list(heights))
                height = np.array(list(heights.values()))
                self._along_scale[index] = np.exp(np.mean(np.log(height))) / height
        config = self.config
        # Per class id (index into CLASS_NAMES; one extra slot for unknown ids).
        self._class_extra = np.array(
            [config.class_measurement_sigma_m.get(name, 0.0) for name in CLASS_NAMES] + [0.0]
        )
        # Gate caps and cluster radii scale with the class's size relative to a person.
        self._class_scale = np.hypot(self._class_extra, config.measurement_sigma_m) / (
            config.measurement_sigma_m
        )
        self._class_acceleration = np.array(
            [config.class_acceleration_sigma.get(name, config.acceleration_sigma)
             for name in CLASS_NAMES] + [config.acceleration_sigma]
        )
        # How far an object may move per second, to widen the gate of a detection captured
        # a little before or after the window's time (before its track's velocity is known
        # to compensate it): the initial velocity uncertainty, scaled like the acceleration.
        self._class_speed = (
            config.initial_velocity_sigma * self._class_acceleration / config.acceleration_sigma
        )
        self._windows = WindowBuffer(
            len(self.camera_ids), config.max_window_s, config.window_fraction
        )
        self._clock = ClockModel(
            len(self.camera_ids), config.clock_tolerance_s, config.max_clock_offset_s,
            estimate=config.estimate_clocks,
        )
        self.reset()

    def _class_slot(self, class_id: np.ndarray) -> np.ndarray:
        class_id = np.asarray(class_id, np.int64)
        return np.where((class_id >= 0) & (class_id < len(CLASS_NAMES)), class_id,
                        len(CLASS_NAMES))

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._object_covariance = self.config.object_sigma_m**2 * np.eye(2)
        self._time: float | None = None
        self._next_id = 1
        self._ids = np.zeros(0, np.int64)  # -1 while tentative
        self._class = np.zeros(0, np.int64)
        self._noise = NoiseModel(
            self.config.measurement_sigma_m, self.config.along_sigma_per_distance,
            self.config.sigma_per_distance,
        )
        self._state = np.zeros((0, 4))
        self._covariance = np.zeros((0, 4, 4))
        models = len(self.config.model_sojourn_s)
        self._mode_state = np.zeros((0, models, 4))
        self._mode_covariance = np.zeros((0, models, 4, 4))
        self._mode_probability = np.zeros((0, models))
        self._evidence = np.zeros(0, np.int64)
        self._last_seen = np.zeros(0)
        # When each camera last saw each track (-inf: never), for corroboration.
        self._seen_by = np.zeros((0, len(self.camera_ids)))
        self._windows.reset()
        self._clock.reset()
        self._reported: dict[int, set[int]] = {}
        self._clock_turn = 0

    @property
    def track_count(self) -> int:
        """Live tracks, tentative ones included."""
        return len(self._ids)

    def get_state(self) -> dict:
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

    # ------------------------------------------------------------------ update
    def update(self, timestamp: float, messages: Sequence[CameraMessage]) -> Tracks:
        """Take the messages of one released group and fuse every window now complete.

        Messages are fused in windows of nearby clock-corrected capture times (see
        :mod:`cblrs.matching.timing`), each at its own capture time, so the rows returned
        may belong to earlier groups, and a window waits until no message can still join it;
        :meth:`flush` fuses what waits at the end of a stream.

        Args:
            timestamp: every message captured (by the cameras' own clocks) at or before this
                has been delivered, in this call or earlier (the latest capture time among
                ``messages`` when groups are released in capture order), seconds.
            messages: messages from any subset of the cameras, each camera's in capture order.

        Returns:
            One row per confirmed track and fused window (frame: the window's newest frame).
        """
        for message in messages:
            camera = self._cameras.get(message.camera_id)
            if camera is None:
                raise MatcherError(
                    f"message from unknown camera {message.camera_id!r}; "
                    f"known: {', '.join(self._cameras)}."
                )
            self._windows.add(camera, message)
        self._windows.advance(float(timestamp))
        return self._drain(final=False)

    def flush(self) -> Tracks:
        """Fuse every message still waiting (the stream has ended); the rows of those windows."""
        return self._drain(final=True)

    def clock_report(self) -> dict[str, dict[str, Any]]:
        """Per camera: estimated clock offset (seconds, positive: ahead of the others), its
        uncertainty, whether it is beyond the tolerance, and counters (see
        :meth:`cblrs.matching.clock.ClockModel.report`)."""
        return self._clock.report(self.camera_ids)

    def clock_events(self) -> list[dict[str, Any]]:
        """Clock events since the last call: ``{"camera", "kind", "offset_s", "time_s"}``."""
        return [
            {"camera": self.camera_ids[event.camera], "kind": event.kind,
             "offset_s": event.offset_s, "time_s": event.time_s}
            for event in self._clock.events()
        ]

    @property
    def waiting(self) -> int:
        """Messages received but not fused yet (their window is not complete)."""
        return len(self._windows)

    def _drain(self, final: bool) -> Tracks:
        parts = []
        while (window := self._windows.next_window(self._clock.offsets, final)) is not None:
            parts.append(self._fuse_window(window))
        return parts[0] if len(parts) == 1 else Tracks.concatenate(parts)

    def _fuse_window(self, window: Window) -> Tracks:
        """Fuse one window: each message at its own corrected capture time."""
        times = window.times
        timestamp = float(times.max())
        if self._time is not None and timestamp < self._time:
            timestamp = self._time  # late messages are fused at the tracker's time
        fresh = times >= timestamp - self.config.max_lag_s
        for camera in window.cameras[~fresh].tolist():
            self._clock.stale(camera)
        if not fresh.all():
            window = Window([m for m, ok in zip(window.messages, fresh.tolist(), strict=True)
                             if ok], window.cameras[fresh], times[fresh], window.end)
            times = window.times
            if not len(times):
                return Tracks.empty()
        messages = window.messages
        # Capture time of each camera's message relative to the window's time (<= 0).
        lag_of_camera = np.zeros(len(self.camera_ids))
        lag_of_camera[window.cameras] = times - timestamp
        raw_time_of_camera = np.zeros(len(self.camera_ids))
        raw_time_of_camera[window.cameras] = [message.timestamp for message in messages]

        raw = decode_messages(self.planes, self._cameras, messages)
        lag = lag_of_camera[raw.camera]
        self._predict(timestamp)
        covariance = self._measurement_covariance(raw)
        base_covariance = covariance
        slot = self._class_slot(raw.class_id)
        if np.any(lag != 0):
            # Until a detection is given a track, its motion over its lag is unknown: widen
            # its gate by how far the class moves in that time.
            covariance = covariance + ((lag * self._class_speed[slot]) ** 2)[:, None, None] * (
                np.eye(2)[None])
        plain = self._class_extra[slot] == 0
        observed = raw
        if plain.any():
            # Box bottoms are not exactly the feet: remove the learned along-ray bias.
            shift = self._noise.bias(self._distance, self._along_distance)
            observed = dataclasses.replace(
                raw, world_xy=raw.world_xy - np.where(plain, shift, 0.0)[:, None]
                * self._direction
            )

        assigned = self._associate(observed, covariance)
        assigned = self._join_observed(observed, covariance, assigned)
        matched = assigned >= 0
        located_xy = observed.world_xy
        if matched.any() and np.any(lag[matched] != 0):
            # Each view shows its track where it was at the view's capture time: move it
            # along the track's velocity to the window's time.
            rows = assigned[matched]
            motion = lag[matched, None] * self._state[rows, 2:4]
            observed = dataclasses.replace(observed, world_xy=observed.world_xy.copy())
            observed.world_xy[matched] -= motion
            raw = dataclasses.replace(raw, world_xy=raw.world_xy.copy())
            raw.world_xy[matched] -= motion
            covariance = base_covariance.copy()
            covariance[matched] += (lag[matched] ** 2)[:, None, None] * (
                self._covariance[rows, 2:4, 2:4])
        if self.config.adapt_noise:
            self._noise.learn(raw.world_xy, self._distance, np.where(plain, assigned, -1),
                              self._direction, self._along_distance)
        track_count = len(self._ids)
        seen_now = np.zeros(track_count, dtype=bool)
        report_camera = np.full(track_count, -1, np.int64)
        report_box = np.full((track_count, 4), np.nan)
        cameras_of_track = np.zeros((track_count, len(self.camera_ids)), dtype=bool)
        if matched.any():
            rows = assigned[matched]
            self._seen_by[rows, observed.camera[matched]] = timestamp
            self._learn_clocks(observed, base_covariance, matched, rows, timestamp)
            fused_xy, fused_covariance, seen_now = fuse(
                rows, track_count, observed.world_xy[matched], covariance[matched]
            )
            (self._mode_state[seen_now], self._mode_covariance[seen_now],
             self._mode_probability[seen_now]) = kalman.update_models(
                self._mode_state[seen_now], self._mode_covariance[seen_now],
                self._mode_probability[seen_now], fused_xy[seen_now],
                fused_covariance[seen_now] + self._object_covariance,
            )
            self._state[seen_now], self._covariance[seen_now] = kalman.combine(
                self._mode_state[seen_now], self._mode_covariance[seen_now],
                self._mode_probability[seen_now],
            )
            self._evidence += np.bincount(rows, minlength=track_count)
            self._last_seen[seen_now] = timestamp
            cameras_of_track[rows, observed.camera[matched]] = True
            report_camera, report_box = self._largest_boxes(observed, matched, rows, track_count)
        else:
            self._clock.corroboration(observed.camera, np.zeros(len(observed), dtype=bool))

        births = self._birth(_subset(observed, ~matched), covariance[~matched], timestamp)
        seen_now = np.concatenate([seen_now, np.ones(births, dtype=bool)])
        report_camera = np.concatenate([report_camera, self._birth_camera])
        report_box = np.concatenate([report_box, self._birth_box])
        cameras_of_track = np.concatenate([cameras_of_track, self._birth_cameras])

        keep = self._merge_duplicates(seen_now, cameras_of_track)
        keep &= self._alive(timestamp)
        self._select(keep)
        seen_now, report_camera, report_box = seen_now[keep], report_camera[keep], report_box[keep]

        newly_confirmed = (self._ids < 0) & (self._evidence >= self.config.confirm_evidence)
        count = int(newly_confirmed.sum())
        self._ids[newly_confirmed] = self._next_id + np.arange(count)
        self._next_id += count
        report = (self._ids >= 0) & (
            seen_now | (timestamp - self._last_seen <= self.config.report_coasting_s)
        )
        self._record_for_clocks(timestamp, seen_now & (self._ids >= 0), located_xy,
                                observed.camera, raw_time_of_camera)
        return self._report_instants(report, report_camera, report_box, window, timestamp)

    def _report_instants(
        self, report: np.ndarray, report_camera: np.ndarray, report_box: np.ndarray,
        window: Window, timestamp: float,
    ) -> Tracks:
        """Rows of the reported tracks at each capture instant of the window.

        An instant is a frame number: the window's messages of one frame (cameras numbering
        frames alike, as data sets do) are one instant, at their mean corrected capture time;
        a window holding the frames of cameras at different rates reports each. The state is
        at the window's latest capture time and is moved back along the track's velocity.
        A track is reported at most once per frame: cameras whose clocks disagree by about
        a frame can put one frame's messages in two windows.
        """
        frame_list = [int(message.frame) for message in window.messages]
        distinct = sorted(set(frame_list))
        frames = np.asarray(frame_list, np.int64)
        parts = []
        for frame in distinct:
            reported = self._reported.get(frame)
            if reported is None:
                reported = self._reported[frame] = set()
                if len(self._reported) > _REPORTED_FRAMES:
                    del self._reported[next(iter(self._reported))]
            mask = report & ~np.isin(self._ids, list(reported)) if reported else report
            order = np.argsort(self._ids[mask], kind="stable")
            rows = np.flatnonzero(mask)[order]
            reported.update(self._ids[rows].tolist())
            instant = float(window.times[frames == frame].mean()) if len(distinct) > 1 else (
                float(window.times.mean()))
            position = self._state[rows, :2]
            if instant != timestamp:
                position = position + (instant - timestamp) * self._state[rows, 2:4]
            parts.append(Tracks(
                frame=np.full(len(rows), frame),
                timestamp=np.full(len(rows), instant),
                track_id=self._ids[rows],
                world_xy=position,
                camera_id=report_camera[rows],
                xyxy=report_box[rows],
                class_id=self._class[rows],
            ))
        return parts[0] if len(parts) == 1 else Tracks.concatenate(parts)

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

    # ------------------------------------------------------------------ steps
    def _predict(self, timestamp: float) -> None:
        if self._time is not None:
            # Messages of slightly different timestamps can arrive out of order; a late
            # one is treated as simultaneous rather than rewinding the filter.
            dt = max(0.0, timestamp - self._time)
            if dt > 0 and len(self._ids):
                acceleration = self._class_acceleration[self._class_slot(self._class)]
                self._mode_state, self._mode_covariance, self._mode_probability = (
                    kalman.predict_models(
                        self._mode_state, self._mode_covariance, self._mode_probability, dt,
                        acceleration[:, None]
                        * np.asarray(self.config.model_acceleration_factors)[None],
                        np.asarray(self.config.model_sojourn_s),
                    )
                )
                self._state, self._covariance = kalman.combine(
                    self._mode_state, self._mode_covariance, self._mode_probability
                )
            self._time = max(self._time, timestamp)
        else:
            self._time = timestamp

    def _camera_rays(self, observed: Observations) -> tuple[np.ndarray, np.ndarray]:
        """(N,) metres from each detection's camera (0 where the camera is not placed) and
        (N, 2) unit vectors from the camera to the detection ((1, 0) where unknown)."""
        offset = observed.world_xy - self._camera_xy[observed.camera]
        distance = np.linalg.norm(offset, axis=1)
        known = np.isfinite(distance) & (distance > 0)
        direction = np.zeros_like(offset)
        direction[:, 0] = 1.0
        direction[known] = offset[known] / distance[known, None]
        return np.where(known, distance, 0.0), direction

    def _measurement_covariance(self, observed: Observations) -> np.ndarray:
        """(N, 2, 2) ground covariance of each detection, elongated along its camera's ray.

        Also sets ``_distance``, ``_direction`` and ``_sigma`` (the largest standard
        deviation of each detection, for neighbour searches).
        """
        self._distance, self._direction = self._camera_rays(observed)
        self._along_distance = self._distance * self._along_scale[observed.camera]
        extra = self._class_extra[self._class_slot(observed.class_id)] ** 2
        along, lateral = self._noise.variances(self._distance, self._along_distance)
        # The model may learn that cameras agree closely; the floor keeps one camera from
        # being trusted without limit.
        floor = self.config.minimum_sigma_m**2
        along = np.maximum(along, floor) + extra
        lateral = np.maximum(lateral, floor) + extra
        self._sigma = np.sqrt(np.maximum(along, lateral))
        return ray_covariance(self._direction, along, lateral)

    def _associate(self, observed: Observations, covariance: np.ndarray) -> np.ndarray:
        """Track row of each detection (-1: none); one detection per camera per track.

        Precise detections are first grouped across cameras and each group is assigned to a
        track as a whole (:meth:`_associate_groups`): when two people walk side by side,
        cameras deciding one by one could each pick differently and blend them. The rest
        is assigned camera by camera.
        """
        count, track_count = len(observed), len(self._ids)
        if count == 0 or track_count == 0:
            return np.full(count, -1, np.int64)
        assigned = self._associate_groups(observed, covariance)
        rest = np.flatnonzero(assigned < 0)
        if len(rest) == 0:
            return assigned
        taken = np.zeros((track_count, len(self.camera_ids)), dtype=bool)
        taken[assigned[assigned >= 0], observed.camera[assigned >= 0]] = True
        # A detection whose gate component holds one track and at most one detection per
        # camera is assigned alike in every camera order: it takes that track directly (if
        # more likely than leaving it unassigned), and only contested detections go through
        # the camera-by-camera assignment below. (One camera has a single order anyway.)
        contested = np.ones(len(rest), dtype=bool)
        if len(np.unique(observed.camera[rest])) > 1:
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
        cameras = np.unique(rest_camera)
        precision = np.array([np.median(self._sigma[rest[rest_camera == one]])
                              for one in cameras.tolist()])
        order = cameras[np.argsort(precision, kind="stable")].tolist()
        best = self._associate_in_order(observed, covariance, assigned, rest, taken, order)
        if self.config.association_orders > 1 and len(order) > 1:
            # The camera order is a heuristic and an early wrong choice propagates to the
            # cameras after it. Assign again in other orders (the reverse first, then
            # rotations) and keep, in each group of tracks and detections where the
            # assignments differ, the one that explains them more likely.
            orders = [order[::-1]] + [order[k:] + order[:k] for k in range(1, len(order))]
            orders = orders[: self.config.association_orders - 1] if contested.any() else []
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
        track_count = len(self._ids)
        node_count = len(rest) + track_count
        graph = coo_matrix(
            (np.ones(len(rows)), (rows, len(rest) + columns)), shape=(node_count, node_count)
        )
        _, label = connected_components(graph, directed=False)
        size = int(label.max()) + 1
        tracks_in = np.bincount(label[len(rest):], minlength=size)
        detection_label = label[: len(rest)]
        camera_count = len(self.camera_ids)
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
        state, state_covariance = self._state.copy(), self._covariance.copy()
        track_count = len(self._ids)
        unassigned = assigned < 0
        spare = covariance + self._object_covariance
        detection_cost = np.where(
            unassigned,
            self.config.gate_sigmas**2
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
                          + self._object_covariance)
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
        track_count = len(self._ids)
        rest_camera = observed.camera[rest]
        # Cameras are processed one after the other, as a Kalman filter processes
        # independent sensors: each camera's detections are assigned against the tracks
        # as already corrected by the cameras before it, most precise camera first. A
        # camera that sees two people side by side along its ray cannot tell them apart,
        # but one looking across that ray can, and its correction is then used.
        state, state_covariance = self._state, self._covariance
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
                if state is self._state:
                    state, state_covariance = state.copy(), state_covariance.copy()
                tracks = chosen[ok]
                state[tracks], state_covariance[tracks] = kalman.update(
                    state[tracks], state_covariance[tracks], observed.world_xy[mine[ok]],
                    covariance[mine[ok]],
                )
        for _ in range(self.config.refine_passes if len(order) > 1 else 0):
            for one in order:
                # Revisit each camera against the tracks corrected by all other cameras.
                others = (assigned >= 0) & (observed.camera != one)
                position, fused_covariance, present = fuse(
                    assigned[others], track_count, observed.world_xy[others], covariance[others]
                )
                state, state_covariance = self._state.copy(), self._covariance.copy()
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
        spare = covariance + self._object_covariance
        return self.config.gate_sigmas**2 + np.log(
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
        cap = self.config.max_gate_m * self._class_scale[self._class_slot(class_id)]
        # A detection reaches as far as its own noise along its ray allows (a far view is
        # metres uncertain along the ray); the Mahalanobis gate still bounds it across.
        cap = np.maximum(cap, self.config.gate_sigmas * largest_sigma(covariance))
        state = self._state if state is None else state
        state_covariance = self._covariance if state_covariance is None else state_covariance
        rows, columns = close_pairs(world_xy, state[:, :2], cap)
        rows, columns = _same_class(rows, columns, class_id, self._class)
        innovation = (state_covariance[columns, :2, :2] + covariance[rows]
                      + self._object_covariance)
        determinant = (innovation[:, 0, 0] * innovation[:, 1, 1]
                       - innovation[:, 0, 1] * innovation[:, 1, 0])
        mahalanobis = mahalanobis_squared(world_xy[rows] - state[columns, :2], innovation)
        inside = mahalanobis <= self.config.gate_sigmas**2
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
        if self.config.group_radius_m <= 0:
            return assigned
        slot = self._class_slot(observed.class_id)
        sigma = np.sqrt(self._noise.variance(self._distance, self._along_distance)
                        + self._class_extra[slot] ** 2)
        limit = self.config.group_radius_m * self._class_scale[slot]
        precise = np.flatnonzero(self.config.cluster_sigmas * np.sqrt(2.0) * sigma <= limit)
        if len(precise) < 2:
            return assigned
        labels = cluster_detections(
            observed.world_xy[precise], observed.camera[precise], self._sigma[precise],
            self.config.cluster_sigmas, observed.class_id[precise],
            covariance=covariance[precise],
        )
        size = np.bincount(labels)
        grouped = size[labels] >= 2
        if not grouped.any():
            return assigned
        members, labels = precise[grouped], labels[grouped]
        _, labels = np.unique(labels, return_inverse=True)
        labels = labels.reshape(-1)
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
        track_count = len(self._ids)
        tracks = assigned[matched]
        fused, fused_covariance, present = fuse(
            tracks, track_count, observed.world_xy[matched], covariance[matched]
        )
        seen = np.flatnonzero(present)
        fused, fused_covariance = fused[seen], fused_covariance[seen]
        taken = np.zeros((track_count, len(self.camera_ids)), dtype=bool)
        taken[tracks, observed.camera[matched]] = True

        slots = self._class_slot(observed.class_id[leftover])
        floor = self.config.cluster_radius_m * self._class_scale[slots]
        fused_largest = float(np.max(fused_covariance[:, 0, 0] + fused_covariance[:, 1, 1]))
        largest = np.maximum(
            floor,
            self.config.cluster_sigmas * np.sqrt(self._sigma[leftover] ** 2 + fused_largest),
        )
        rows, columns = close_pairs(observed.world_xy[leftover], fused, largest)
        rows, columns = _same_class(rows, columns, observed.class_id[leftover],
                                    self._class[seen])
        difference = observed.world_xy[leftover[rows]] - fused[columns]
        distance = np.linalg.norm(difference, axis=1)
        normalised = np.sqrt(mahalanobis_squared(
            difference, covariance[leftover[rows]] + fused_covariance[columns]
        ))
        allowed = (
            (normalised <= self.config.cluster_sigmas) | (distance <= floor[rows])
        ) & ~taken[seen[columns], observed.camera[leftover[rows]]]
        joined = assign_per_camera(
            rows[allowed], columns[allowed], normalised[allowed], observed.camera[leftover],
            len(self.camera_ids),
        )
        assigned = assigned.copy()
        ok = joined >= 0
        assigned[leftover[ok]] = seen[joined[ok]]
        return assigned

    @staticmethod
    def _largest_boxes(
        observed: Observations, matched: np.ndarray, rows: np.ndarray, track_count: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Camera and box of each track's largest assigned box (the closest, best view)."""
        boxes = observed.xyxy[matched]
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        order = np.lexsort((area, rows))  # by track, then by area ascending
        last_of_track = np.r_[rows[order][1:] != rows[order][:-1], True]
        best = order[last_of_track]
        camera = np.full(track_count, -1, np.int64)
        box = np.full((track_count, 4), np.nan)
        camera[rows[best]] = observed.camera[matched][best]
        box[rows[best]] = boxes[best]
        return camera, box

    def _birth(self, leftovers: Observations, covariance: np.ndarray, timestamp: float) -> int:
        """Start a tentative track per cross-camera cluster of unassigned detections."""
        sigma = largest_sigma(covariance)
        labels = cluster_detections(
            leftovers.world_xy, leftovers.camera, sigma,
            self.config.cluster_sigmas, leftovers.class_id,
            self.config.cluster_radius_m
            * self._class_scale[self._class_slot(leftovers.class_id)],
            covariance=covariance,
        )
        count = int(labels.max()) + 1 if len(labels) else 0
        camera_count = len(self.camera_ids)
        self._birth_cameras = np.zeros((count, camera_count), dtype=bool)
        self._birth_camera = np.full(count, -1, np.int64)
        self._birth_box = np.full((count, 4), np.nan)
        if count == 0:
            return 0
        position, position_covariance, _ = fuse(
            labels, count, leftovers.world_xy, covariance
        )
        state = np.zeros((count, 4))
        state[:, :2] = position
        covariance = kalman.initial_covariance(
            count, position_covariance + self._object_covariance,
            self.config.initial_velocity_sigma,
        )
        self._birth_cameras[labels, leftovers.camera] = True
        self._birth_camera, self._birth_box = self._largest_boxes(
            leftovers, np.ones(len(labels), dtype=bool), labels, count
        )
        self._ids = np.concatenate([self._ids, np.full(count, -1, np.int64)])
        cluster_class = np.zeros(count, np.int64)
        cluster_class[labels] = leftovers.class_id  # one class per cluster
        self._class = np.concatenate([self._class, cluster_class])
        self._state = np.concatenate([self._state, state])
        self._covariance = np.concatenate([self._covariance, covariance])
        models = len(self.config.model_sojourn_s)
        self._mode_state = np.concatenate(
            [self._mode_state, np.repeat(state[:, None], models, axis=1)])
        self._mode_covariance = np.concatenate(
            [self._mode_covariance, np.repeat(covariance[:, None], models, axis=1)])
        self._mode_probability = np.concatenate([
            self._mode_probability,
            np.tile(kalman.stationary_probability(np.asarray(self.config.model_sojourn_s)),
                    (count, 1)),
        ])
        self._evidence = np.concatenate([self._evidence, np.bincount(labels, minlength=count)])
        self._last_seen = np.concatenate([self._last_seen, np.full(count, timestamp)])
        self._seen_by = np.concatenate([
            self._seen_by, np.where(self._birth_cameras, timestamp, -np.inf)])
        return count

    def _merge_duplicates(self, seen_now: np.ndarray, cameras_of_track: np.ndarray) -> np.ndarray:
        """Keep-mask dropping the younger of two confirmed tracks that are one object."""
        keep = np.ones(len(self._ids), dtype=bool)
        if self.config.merge_radius_m <= 0:
            return keep
        candidates = np.flatnonzero(seen_now & (self._ids >= 0))
        if len(candidates) < 2:
            return keep
        position = self._state[candidates, :2]
        first, second = close_pairs(
            position, position, np.full(len(candidates), self.config.merge_radius_m),
            strict=True,
        )
        upper = first < second
        first, second = candidates[first[upper]], candidates[second[upper]]
        disjoint = ~(cameras_of_track[first] & cameras_of_track[second]).any(axis=1)
        for one, other in zip(first[disjoint].tolist(), second[disjoint].tolist(), strict=True):
            if keep[one] and keep[other]:
                younger = one if self._ids[one] > self._ids[other] else other
                keep[younger] = False
        return keep

    def _alive(self, timestamp: float) -> np.ndarray:
        age = timestamp - self._last_seen
        limit = np.where(self._ids >= 0, self.config.max_age_s, self.config.tentative_max_age_s)
        return age <= limit

    def _select(self, keep: np.ndarray) -> None:
        self._ids = self._ids[keep]
        self._class = self._class[keep]
        self._state = self._state[keep]
        self._covariance = self._covariance[keep]
        self._mode_state = self._mode_state[keep]
        self._mode_covariance = self._mode_covariance[keep]
        self._mode_probability = self._mode_probability[keep]
        self._evidence = self._evidence[keep]
        self._last_seen = self._last_seen[keep]
        self._seen_by = self._seen_by[keep]


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


def _subset(observed: Observations, mask: np.ndarray) -> Observations:
    return Observations(
        world_xy=observed.world_xy[mask], colour=observed.colour[mask],
        camera=observed.camera[mask], xyxy=observed.xyxy[mask],
        confidence=observed.confidence[mask], class_id=observed.class_id[mask],
    )


class NoiseModel:
    """Online estimate of the detector's ground-position noise, along and across the ray.

    A camera locates a foot point by the ray through its pixel; a pixel error along the
    image's vertical moves the point along the viewing direction by far more than the same
    error across it (the ray grazes the ground), so one camera's error is an ellipse
    elongated along the direction from the camera to the point. Per axis of that frame:

    * along the ray: ``a**2 + (b * distance)**2``;
    * across it: ``e**2 + (c * distance)**2``.

    Two cameras' detections of one object at one instant differ by the sum of two
    independent errors, so the expected outer product of the difference is the sum of the
    two covariances, which is linear in ``(a**2, b**2, e**2, c**2)``. The model is the
    non-negative least-squares fit of those three equations per pair, each pair whitened
    by its covariance under the current model (Fisher scoring for variance components),
    over recent pairs (exponentially forgotten), anchored by a prior worth a few dozen
    pairs at 5 and 25 m.
    A difference is shrunk to at most three standard deviations (in the current model's
    metric) so one wrong association cannot inflate the noise. Without camera positions,
    distances are zero and the model is isotropic.
    """

    prior_pairs = 40.0
    forget_per_pair = 0.9995  # memory of a few thousand pairs
    minimum_sigma_m = 0.02
    prior_distances_m = (5.0, 25.0)
    clip_sigmas = 3.0

    def __init__(
        self, sigma_m: float, sigma_per_distance: float,
        lateral_per_distance: float | None = None,
    ):
        lateral = sigma_per_distance if lateral_per_distance is None else lateral_per_distance
        self.prior = np.array([sigma_m**2, sigma_per_distance**2, sigma_m**2, lateral**2])
        self.reset()

    def reset(self) -> None:
        self.normal = np.zeros((4, 4))
        self.moment = np.zeros(4)
        weight = self.prior_pairs / len(self.prior_distances_m)
        for distance in self.prior_distances_m:
            # A pseudo pair of two cameras looking along x: x holds the along-ray
            # variances, y the across-ray ones. Like every pair it is whitened by its own
            # predicted covariance (see :meth:`learn`), so it weighs as much as
            # ``weight`` real pairs whatever the size of the noise.
            features = np.array([[2.0, 2.0 * distance**2, 0.0, 0.0],
                                 [0.0, 0.0, 2.0, 2.0 * distance**2]])
            features = features / (features @ self.prior)[:, None]
            self.normal += weight * features.T @ features
            self.moment += weight * features.T @ np.ones(2)
        self.coefficients = self.prior.copy()
        # Along-ray bias ``q * along_distance``, zero a priori (worth prior_pairs pairs).
        self.bias_normal = self.prior_pairs * self.prior_distances_m[1] ** 2
        self.bias_moment = 0.0
        self.bias_per_distance = 0.0

    def bias(self, distance: np.ndarray, along_distance: np.ndarray | None = None) -> np.ndarray:
        """(N,) mean error along the ray (metres, positive: beyond the object) at (N,) metres.

        A camera's foot points can all land a little too far or too near (box bottoms
        drawn below or above the feet, a footprint whose near edge is the box bottom); a
        box edge off by a fixed fraction of the box height moves the point along the ground
        in proportion to ``along_distance`` (distance / camera height), as the noise does.
        Cameras looking from different sides disagree by it, so it is learned like the noise.
        """
        along_distance = distance if along_distance is None else along_distance
        return self.bias_per_distance * along_distance

    def _learn_bias(
        self, world_xy: np.ndarray, distance: np.ndarray, along_distance: np.ndarray,
        direction: np.ndarray, first: np.ndarray, second: np.ndarray,
    ) -> np.ndarray:
        """Update the bias from pairs ``(first, second)``; return the corrected positions.

        The difference of two views of one object is ``q (g_1 - g_2)`` on average (``g =
        along_distance * u``, ``u`` the unit rays): a least-squares fit of ``q``.
        """
        del distance
        reach = along_distance[:, None] * direction
        feature = reach[first] - reach[second]
        difference = world_xy[first] - world_xy[second]
        decay = self.forget_per_pair ** len(first)
        self.bias_normal = decay * self.bias_normal + float(np.sum(feature**2))
        self.bias_moment = decay * self.bias_moment + float(np.sum(feature * difference))
        self.bias_per_distance = self.bias_moment / self.bias_normal
        return world_xy - self.bias_per_distance * reach

    def variances(
        self, distance: np.ndarray, along_distance: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(N,) along-ray and (N,) across-ray variances, square metres.

        Args:
            distance: (N,) metres from the camera.
            along_distance: (N,) the distance the along-ray term grows with (for example
                scaled by the camera's height); ``distance`` when None.
        """
        along_distance = distance if along_distance is None else along_distance
        along = self.coefficients[0] + self.coefficients[1] * along_distance**2
        return along, self.coefficients[2] + self.coefficients[3] * distance**2

    def variance(
        self, distance: np.ndarray, along_distance: np.ndarray | None = None
    ) -> np.ndarray:
        """(N,) the larger of the two variances, square metres (see :meth:`variances`)."""
        along, lateral = self.variances(distance, along_distance)
        return np.maximum(along, lateral)

    def covariance(
        self, distance: np.ndarray, direction: np.ndarray,
        along_distance: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, 2, 2) covariances, square metres, for (N,) distances and (N, 2) unit rays."""
        along, lateral = self.variances(distance, along_distance)
        return ray_covariance(direction, along, lateral)

    def learn(
        self, world_xy: np.ndarray, distance: np.ndarray, track: np.ndarray,
        direction: np.ndarray | None = None, along_distance: np.ndarray | None = None,
    ) -> None:
        """Update from detections assigned to tracks.

        Args:
            world_xy: (N, 2) metres.
            distance: (N,) metres from each detection's camera (0: unknown).
            track: (N,) int64 track of each detection, -1 to ignore.
            direction: (N, 2) unit vectors from the camera to each detection; None treats
                the noise as isotropic (along and across share their distance terms).
            along_distance: (N,) what the along-ray term grows with (default ``distance``).
        """
        rows = np.flatnonzero(track >= 0)
        if len(rows) < 2:
            return
        rows = rows[np.argsort(track[rows], kind="stable")]
        same = track[rows[1:]] == track[rows[:-1]]
        first, second = rows[:-1][same], rows[1:][same]
        if len(first) == 0:
            return
        along_distance = distance if along_distance is None else along_distance
        if direction is None:
            direction = np.zeros((len(world_xy), 2))
            direction[:, 0] = 1.0
            isotropic = True
        else:
            isotropic = False
            world_xy = self._learn_bias(world_xy, distance, along_distance, direction,
                                        first, second)
        # Per pair and coefficient, the (2, 2) matrix it multiplies in the sum of the two
        # covariances: along-ray constant and distance terms, across-ray ones.
        identity = np.eye(2)[None]
        parts = np.zeros((len(first), 4, 2, 2))
        for one in (first, second):
            outer = direction[one][:, :, None] * direction[one][:, None, :]
            squared = (distance[one] ** 2)[:, None, None]
            along_squared = (along_distance[one] ** 2)[:, None, None]
            if isotropic:
                outer = 0.5 * np.broadcast_to(identity, outer.shape)
            parts[:, 0] += outer
            parts[:, 1] += along_squared * outer
            parts[:, 2] += identity - outer
            parts[:, 3] += squared * (identity - outer)
        # Whiten each pair by its covariance under the current model (``L^-1`` of its
        # Cholesky factor): the fit is then Fisher scoring for the variance components,
        # where every pair carries about the same information. Unweighted, the large
        # along-ray variances of far views would drown the small across-ray ones, and
        # the model would take minutes of data to learn how precise the cameras are
        # across their rays.
        covariance = np.einsum("kcij,c->kij", parts, self.coefficients)
        whitening = inverse_cholesky_2x2(covariance)
        parts = whitening[:, None] @ parts @ np.swapaxes(whitening, 1, 2)[:, None]
        difference = np.einsum(
            "kij,kj->ki", whitening, world_xy[first] - world_xy[second]
        )
        # Whitened, the difference of a right association is about unit normal; one far
        # beyond is shrunk so a wrong association cannot inflate the noise.
        squared = np.sum(difference**2, axis=1)
        limit = 2.0 * self.clip_sigmas**2
        with np.errstate(divide="ignore", invalid="ignore"):
            shrink = np.where(squared > limit, np.sqrt(limit / squared), 1.0)
        difference = difference * shrink[:, None]
        root_two = np.sqrt(2.0)
        features = np.stack(
            [parts[:, :, 0, 0], parts[:, :, 1, 1], root_two * parts[:, :, 0, 1]], axis=1
        )  # (K, 3 equations, 4 coefficients)
        target = np.column_stack(
            [difference[:, 0] ** 2, difference[:, 1] ** 2,
             root_two * difference[:, 0] * difference[:, 1]]
        )
        decay = self.forget_per_pair ** len(first)
        flat_features = features.reshape(-1, 4)
        self.normal = decay * self.normal + flat_features.T @ flat_features
        self.moment = decay * self.moment + flat_features.T @ target.reshape(-1)
        self._solve()

    def _solve(self) -> None:
        try:
            root = np.linalg.cholesky(self.normal)
            coefficients, _ = nnls(root.T, np.linalg.solve(root, self.moment))
        except (np.linalg.LinAlgError, RuntimeError):
            return
        coefficients[0] = max(coefficients[0], self.minimum_sigma_m**2)
        coefficients[2] = max(coefficients[2], self.minimum_sigma_m**2)
        self.coefficients = coefficients

    @property
    def sigma_m(self) -> float:
        """Along-ray standard deviation at the camera, metres."""
        return float(np.sqrt(self.coefficients[0]))

    @property
    def lateral_sigma_m(self) -> float:
        """Across-ray standard deviation at the camera, metres."""
        return float(np.sqrt(self.coefficients[2]))

    @property
    def sigma_per_distance(self) -> float:
        """Along-ray standard deviation per metre of distance."""
        return float(np.sqrt(self.coefficients[1]))

    @property
    def lateral_per_distance(self) -> float:
        """Across-ray standard deviation per metre of distance."""
        return float(np.sqrt(self.coefficients[3]))

    def get_state(self) -> dict:
        return {
            "normal": self.normal.tolist(),
            "moment": self.moment.tolist(),
            "coefficients": self.coefficients.tolist(),
            "bias_normal": self.bias_normal,
            "bias_moment": self.bias_moment,
            "bias_per_distance": self.bias_per_distance,
        }

    def set_state(self, state: dict) -> None:
        self.normal = np.asarray(state["normal"], np.float64).reshape(4, 4)
        self.moment = np.asarray(state["moment"], np.float64).reshape(4)
        self.coefficients = np.asarray(state["coefficients"], np.float64).reshape(4)
        self.bias_normal = float(state["bias_normal"])
        self.bias_moment = float(state["bias_moment"])
        self.bias_per_distance = float(state["bias_per_distance"])


def ray_covariance(
    direction: np.ndarray, along_variance: np.ndarray, lateral_variance: np.ndarray
) -> np.ndarray:
    """(N, 2, 2) covariances elongated along unit ``direction`` (N, 2).

    ``along_variance`` and ``lateral_variance`` are (N,) square metres along and across it.
    """
    outer = direction[:, :, None] * direction[:, None, :]
    return (lateral_variance[:, None, None] * np.eye(2)[None]
            + (along_variance - lateral_variance)[:, None, None] * outer)


def largest_sigma(covariance: np.ndarray) -> np.ndarray:
    """(N,) square root of the largest eigenvalue of (N, 2, 2) covariances, metres."""
    half_trace = 0.5 * (covariance[:, 0, 0] + covariance[:, 1, 1])
    spread = np.hypot(0.5 * (covariance[:, 0, 0] - covariance[:, 1, 1]), covariance[:, 0, 1])
    return np.sqrt(half_trace + spread)


def inverse_cholesky_2x2(covariance: np.ndarray) -> np.ndarray:
    """(K, 2, 2) ``L^-1`` of the Cholesky factors ``L L^T`` of (K, 2, 2) SPD matrices.

    ``L^-1 d`` whitens a difference ``d`` of covariance ``L L^T``. Closed form: numpy's
    batched LAPACK calls cost far more than the arithmetic for 2 x 2 matrices.
    """
    first = np.sqrt(covariance[:, 0, 0])
    lower = covariance[:, 1, 0] / first
    second = np.sqrt(covariance[:, 1, 1] - lower * lower)
    inverse = np.zeros_like(covariance)
    inverse[:, 0, 0] = 1.0 / first
    inverse[:, 1, 0] = -lower / (first * second)
    inverse[:, 1, 1] = 1.0 / second
    return inverse


def mahalanobis_squared(difference: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """(K,) ``d^T C^-1 d`` for (K, 2) differences and (K, 2, 2) covariances."""
    a, b, d = covariance[:, 0, 0], covariance[:, 0, 1], covariance[:, 1, 1]
    dx, dy = difference[:, 0], difference[:, 1]
    return (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)


def fuse(
    labels: np.ndarray, count: int, world_xy: np.ndarray, covariance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information-weighted fusion of detections per label.

    Args:
        labels: (N,) int64 in 0..count-1.
        count: number of labels K.
        world_xy: (N, 2) metres.
        covariance: (N, 2, 2) square metres.

    Returns:
        ``(position (K, 2), covariance (K, 2, 2), present (K,) bool)``; rows of absent labels
        are NaN.
    """
    information, _ = kalman.inverse_2x2(covariance)
    weighted = np.einsum("nij,nj->ni", information, world_xy)
    total = np.zeros((count, 2, 2))
    vector = np.zeros((count, 2))
    for row in range(2):
        vector[:, row] = np.bincount(labels, weighted[:, row], count)
        for column in range(2):
            total[:, row, column] = np.bincount(labels, information[:, row, column], count)
    present = np.bincount(labels, minlength=count) > 0
    fused_covariance = np.full((count, 2, 2), np.nan)
    position = np.full((count, 2), np.nan)
    if present.any():
        fused_covariance[present], _ = kalman.inverse_2x2(total[present])
        position[present] = np.einsum(
            "nij,nj->ni", fused_covariance[present], vector[present]
        )
    return position, fused_covariance, present


def close_pairs(
    points_xy: np.ndarray, targets_xy: np.ndarray, radius_m: np.ndarray, strict: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` with ``|points[i] - targets[j]| <= radius[i]``.

    Args:
        points_xy: (N, 2) metres.
        targets_xy: (T, 2) metres.
        radius_m: (N,) metres per point.
        strict: use ``<`` instead of ``<=``.

    Returns:
        ``(rows, columns)``, two (K,) int64 arrays in row-major order.
    """
    if len(points_xy) == 0 or len(targets_xy) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty
    if len(points_xy) * len(targets_xy) <= _DENSE_PAIRS:
        dx = points_xy[:, 0, None] - targets_xy[None, :, 0]
        dy = points_xy[:, 1, None] - targets_xy[None, :, 1]
        squared = dx * dx + dy * dy
        limit = (radius_m * radius_m)[:, None]
        rows, columns = np.nonzero(squared < limit if strict else squared <= limit)
        return rows.astype(np.int64), columns.astype(np.int64)
    # Many tracks: a k-d tree finds the few neighbours without touching all N x T pairs.
    finite_points = np.isfinite(points_xy).all(axis=1)
    finite_targets = np.isfinite(targets_xy).all(axis=1)
    point_index = np.flatnonzero(finite_points)
    target_index = np.flatnonzero(finite_targets)
    pairs = cKDTree(points_xy[point_index]).sparse_distance_matrix(
        cKDTree(targets_xy[target_index]), float(np.max(radius_m)), output_type="ndarray"
    )
    rows = point_index[pairs["i"]]
    columns = target_index[pairs["j"]]
    distance = pairs["v"]
    keep = distance < radius_m[rows] if strict else distance <= radius_m[rows]
    rows, columns = rows[keep], columns[keep]
    order = np.lexsort((columns, rows))
    return rows[order].astype(np.int64), columns[order].astype(np.int64)


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
    _, key_index, per_key = np.unique(column_key, return_inverse=True, return_counts=True)
    trivial = (per_row[rows] == 1) & (per_key[key_index] == 1)
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
    for one_camera in np.unique(pair_camera).tolist():
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
    graph = coo_matrix(
        (np.ones(int(keep.sum())), (source[keep], target[keep])), shape=(node_count, node_count)
    )
    _, label = connected_components(graph, directed=False)
    track_label, detection_label = label[:track_count], label[track_count:]
    involved = np.unique(detection_label[differ])
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
    graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(count, count))
    _, component = connected_components(graph, directed=False)
    size = np.bincount(component)
    edges = np.bincount(component[first], minlength=len(size))
    cameras_in = np.bincount(
        np.unique(component * (int(camera.max()) + 1) + camera) // (int(camera.max()) + 1),
        minlength=len(size),
    )
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
