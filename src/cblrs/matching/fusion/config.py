"""Configuration of the fusion tracker: :class:`FusionConfig` and the per-class defaults.

Every parameter is physical (metres, seconds, m/s, m/s^2), so the same defaults serve 2 fps
data sets and 10 or 20 fps video.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cblrs.detections import CLASS_NAMES, SURE_CONFIDENCE
from cblrs.matching.base import (
    require,
)
from cblrs.matching.clock import DEFAULT_MAX_OFFSET_S, DEFAULT_TOLERANCE_S
from cblrs.matching.timing import (
    DEFAULT_MAX_WINDOW_S,
    DEFAULT_WINDOW_FRACTION,
)

# Vehicles are located less precisely than people (their footprint is metres long and the
# box bottom only bounds it) and turn harder; everything else falls back to the base values.
DEFAULT_CLASS_MEASUREMENT_SIGMA_M: dict[str, float] = {
    "car": 0.7, "truck": 1.0, "bus": 1.2, "bicycle": 0.3, "motorcycle": 0.4,
}
DEFAULT_CLASS_ACCELERATION_SIGMA: dict[str, float] = {
    "car": 5.0, "truck": 2.0, "bus": 2.0, "bicycle": 1.5, "motorcycle": 3.0,
}
DEFAULT_CLASS_TURN_RADIUS_M: dict[str, float] = {
    "car": 5.0, "truck": 8.0, "bus": 9.0, "bicycle": 2.0, "motorcycle": 3.0,
}
"""Smallest turning radius of each vehicle class, metres (people turn on the spot)."""


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
        vehicle_minimum_sigma_m: the same for a vehicle's view refined with its track's
            heading, where it is reported (:mod:`~cblrs.matching.fusion.vehicle_noise`;
            the footprint centre of a class-typical size is off by this much per view
            whatever the cameras' agreement); 0: ``minimum_sigma_m``.
        object_sigma_m: standard deviation of an object's position common to all the views
            of one instant, metres: a person is not a point (where the views' foot points
            fall on the body, where the ground truth marks it) and does not move at exactly
            constant velocity. Cameras' disagreement cannot reveal it, so it is added once to
            each instant's fused observation rather than to every camera's.
        adapt_noise: re-estimate the noise model and the along-ray bias online from the
            disagreement of the cameras that see the same object at the same instant (so the
            same defaults serve exact boxes and a noisy detector); False keeps the initial
            values.
        constant_bias: also learn a constant along-ray bias of people's views beside the
            one proportional to distance: a box's bottom is the near edge of a body, short of
            its centre by about half a body at any distance (a synthetic crowd's 0.26 m).
            Used only when it is short (negative) and explains a clear share of the cameras'
            disagreement (:class:`~cblrs.matching.fusion.noise.NoiseModel`); annotated boxes
            and a noisy detector on WILDTRACK learn none and are unchanged.
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
        class_turn_radius_m: smallest turning radius of each vehicle class, metres
            (``{class name: m}``; classes left out, people, turn on the spot). A moving
            vehicle cannot turn on the spot nor reverse at once: a track of such a class
            whose speed is known takes a detection only if the direction from where it was
            last seen to the detection is within the heading change its speed and this
            radius allow since then (plus the detection's noise). This is what keeps a
            coasting car's track from taking the next car arriving on the opposite lane.
        model_acceleration_factors: the motion model is an interacting multiple-model
            filter: constant-velocity models whose white-noise accelerations are these
            multiples of the class's (people mostly walk steadily, sometimes turn or stop:
            0.25 m/s^2 and 2 m/s^2 for a person); ``(1.0,)`` is a single constant-velocity
            filter.
        model_sojourn_s: mean time spent in each of those models, seconds (one per model).
        initial_velocity_sigma: velocity uncertainty of a new person's track, m/s; other
            classes' scale like their acceleration (``class_acceleration_sigma``: 7.5 m/s
            for a car).
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
        confirm_cameras: a new track is confirmed only once this many cameras have seen it,
            where at least that many cameras cover its position (learned from where each
            camera locates detections, :mod:`~cblrs.matching.fusion.coverage`); where fewer
            do, as many as cover it (at least one). 1: any one camera confirms.
        confirm_moving_mps: a tentative track moving faster than this (m/s, and clearly:
            faster than three standard deviations of its velocity) is confirmed by one
            camera wherever it is. The false positives a detector keeps firing sit still
            (a sign, a bollard, a reflection); a car or a person whom the second camera
            cannot see (an occluder the reference image does not know, a distance where it
            detects nothing) moves. 0: moving tracks need the cameras like any other.
        high_confidence: detections scoring below this (the detector's score, 0..1) are
            low-confidence: they may extend a live track (after the high-confidence ones
            are associated, and only from a camera that gave the track nothing yet) or
            start one together with another camera's view of the same place, never alone
            (:mod:`~cblrs.matching.fusion.low_confidence`). ByteTrack's split (0.5; run the
            detector lower, 0.1, to have low-confidence boxes at all). 0: every detection
            is high-confidence.
        support_ratio: a track not clearly moving whose other covering cameras (all but the
            one that sees it most) could have seen it for ``support_evidence_s``
            camera-seconds and saw it less than this share of that time is neither
            confirmed nor reported (the support stage,
            :mod:`~cblrs.matching.fusion.support`: a detector's persistent false positive,
            seen by one camera where others look). 0: off.
        confirm_support_share: a tentative track at least a second old that needs two
            cameras is confirmed only once the cameras other than its main one have seen it
            for this share of the time its main camera did (one instant of another camera
            does not confirm a false positive one camera has carried for seconds; the
            support stage, :mod:`~cblrs.matching.fusion.support`). 0: off.
        support_evidence_s: camera-seconds the other covering cameras must have had to
            see a track before the support stage judges it.
        support_memory_s: the support stage forgets what the cameras saw over this time
            constant, seconds.
        tentative_max_age_s: a tentative track unseen this long is dropped, seconds.
        max_age_s: a confirmed track unseen this long is dropped, seconds.
        vehicle_footprint: move each vehicle detection along its camera's ray from where its
            box's target pixel lands to the footprint centre that put it there, by the
            class's size and the track's heading (:mod:`~cblrs.matching.fusion.footprint`;
            needs camera heights in ``camera_positions``). People are not moved.
        end_off_plane: a track missed at an instant whose prediction lies off every plane,
            moving away from it, has left the located area and is dropped at once (no camera
            can locate it there); False keeps it coasting for ``max_age_s``.
        stitch_gap_s: a new track born at most this long after a confirmed track was last
            seen may continue it and take its id (the stitching stage,
            :mod:`~cblrs.matching.fusion.stitching`): a confirmed track dropped for being
            unseen too long is kept this long for it, seconds (0: no stitching).
        stitch_delay_s: a new track that may continue a lost one and whose velocity is not
            clearly known yet is held back (tentative, not reported) until its velocity is
            known or this long after its first detection, seconds; 0: decided when it would
            be confirmed, with what is known then (a track two cameras confirm at once is
            not stitched). Ids once reported are never rewritten either way.
        stitch_sigmas: a new track continues a lost one when their (x, y, vx, vy) states are
            within this many standard deviations of each other (Mahalanobis distance under
            the sum of their covariances), and no other pair could be it.
        stitch_coasting: a new person's track may also continue a confirmed track that still
            coasts (unseen now, not dropped yet), even before its velocity is known, where the
            cameras are known to miss people hidden behind others (the occlusion stage's
            learnt miss rate above one half): it takes the id and the coasting track is
            dropped (:mod:`~cblrs.matching.fusion.stitching`).
        stitch_turn_dps: a new person's track whose velocity is known may also continue a
            coasting one it reached by turning: on the arc of constant speed and turn rate
            from where the coasting track was last seen to the new track's heading now, the
            turn at most this many degrees a second, the speeds alike
            (:mod:`~cblrs.matching.fusion.stitching`); 0: off.
        stitch_arc_m: how far off that arc the new track may be, beyond three standard
            deviations of the two positions, metres (a walker turns, then goes straight).
        swap_radius_m: two confirmed tracks of people closer than this open an encounter;
            once they have been farther apart than this for ``swap_settle_s``, they exchange
            ids from then on if their motion before the encounter explains what each saw
            after it better swapped (the swap stage, :mod:`~cblrs.matching.fusion.swaps`),
            metres; 0: off.
        swap_settle_s: how long two tracks must have been apart again before the swap stage
            decides, seconds.
        swap_margin: how much more likely (log-likelihood) the swapped pairing must be,
            log units.
        report_coasting_s: keep reporting the prediction of a confirmed track that was
            missed for at most this long, seconds (0: report only observed tracks).
        report_hidden_s: also report a confirmed track missed for at most this long,
            seconds, at the instants it is hidden: every camera whose view covers its
            predicted position has a detection in front of it (nearer, within
            ``occluder_width_m`` of its bearing), so none could have seen it (a person
            walking behind another in a crowd; :mod:`~cblrs.matching.fusion.occlusion`).
            A track that a covering camera should have seen is not reported. 0: off.
        occluder_width_m: how far beside the line of sight from a camera to a missed
            track a nearer detection still hides it, metres (about a body's width).
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
    vehicle_minimum_sigma_m: float = 0.3
    object_sigma_m: float = 0.1
    adapt_noise: bool = True
    constant_bias: bool = True
    class_measurement_sigma_m: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_MEASUREMENT_SIGMA_M)
    )
    camera_positions: Mapping[str, Sequence[float]] | None = None
    acceleration_sigma: float = 1.0
    class_acceleration_sigma: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_ACCELERATION_SIGMA)
    )
    class_turn_radius_m: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_CLASS_TURN_RADIUS_M)
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
    confirm_cameras: int = 2
    confirm_moving_mps: float = 0.5
    high_confidence: float = SURE_CONFIDENCE
    support_ratio: float = 0.1
    support_evidence_s: float = 2.0
    confirm_support_share: float = 0.25
    support_memory_s: float = 10.0
    tentative_max_age_s: float = 1.0
    max_age_s: float = 2.0
    end_off_plane: bool = True
    vehicle_footprint: bool = True
    stitch_gap_s: float = 3.0
    stitch_delay_s: float = 0.0
    stitch_sigmas: float = 3.0
    stitch_coasting: bool = True
    stitch_turn_dps: float = 180.0
    stitch_arc_m: float = 0.8
    swap_radius_m: float = 1.0
    swap_settle_s: float = 0.5
    swap_margin: float = 7.0
    report_coasting_s: float = 0.0
    report_hidden_s: float = 2.0
    occluder_width_m: float = 0.5
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
            "window_fraction", "max_lag_s", "clock_tolerance_s", "stitch_sigmas",
            "support_evidence_s", "support_memory_s",
        ):
            value = getattr(self, name)
            require(_positive(value), f"{name} must be a positive number, got {value!r}.")
        for name in ("sigma_per_distance", "along_sigma_per_distance", "merge_radius_m",
                     "report_coasting_s", "report_hidden_s", "occluder_width_m",
                     "object_sigma_m", "group_radius_m", "vehicle_minimum_sigma_m",
                     "max_clock_offset_s", "stitch_gap_s", "stitch_delay_s",
                     "swap_radius_m", "swap_settle_s", "swap_margin", "stitch_turn_dps",
                     "stitch_arc_m"):
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
        for name in ("adapt_noise", "constant_bias", "estimate_clocks", "end_off_plane",
                     "stitch_coasting"):
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
        require(
            isinstance(self.confirm_cameras, int) and not isinstance(self.confirm_cameras, bool)
            and self.confirm_cameras >= 1,
            f"confirm_cameras must be a whole number >= 1, got {self.confirm_cameras!r}.",
        )
        require(
            isinstance(self.confirm_moving_mps, (int, float)) and self.confirm_moving_mps >= 0,
            f"confirm_moving_mps must be a number >= 0, got {self.confirm_moving_mps!r}.",
        )
        require(
            isinstance(self.high_confidence, (int, float))
            and not isinstance(self.high_confidence, bool)
            and 0.0 <= self.high_confidence <= 1.0,
            f"high_confidence must be a number within 0..1, got {self.high_confidence!r}.",
        )
        require(
            isinstance(self.support_ratio, (int, float))
            and not isinstance(self.support_ratio, bool) and 0.0 <= self.support_ratio <= 1.0,
            f"support_ratio must be a number within 0..1, got {self.support_ratio!r}.",
        )
        require(
            isinstance(self.confirm_support_share, (int, float))
            and not isinstance(self.confirm_support_share, bool)
            and math.isfinite(self.confirm_support_share) and self.confirm_support_share >= 0,
            "confirm_support_share must be a number >= 0, "
            f"got {self.confirm_support_share!r}.",
        )
        for name in ("class_measurement_sigma_m", "class_acceleration_sigma",
                     "class_turn_radius_m"):
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
