"""Where a vehicle is reported: a turning filter on its refined views (part of step 5 of the
fusion tracker's update, for vehicles).

:class:`~cblrs.matching.fusion.vehicle_noise.VehicleNoise` gives the views of a vehicle whose
heading is known their sharp, learned noise. Corrected from the tracker's own
constant-velocity prediction, which lags and drifts outwards while a car turns (on a
roundabout's ring it turns all the time), the reported position then follows each
instant's views and their noise: with a detector's jittered boxes, two or three views of a
car scatter a couple of decimetres, and one view alone lies metres along its camera's ray.

:class:`TurnFilter` runs, for each such car (:data:`TURNING_CLASSES`; other vehicles keep
each instant's correction), a second filter on those views alone: a
coordinated-turn (CTRV) model, state ``(x, y, speed, heading, turn rate)``, which carries a
car round an arc instead of along its tangent, so it can average several instants' views
without lagging. Its noise is the class's: white longitudinal acceleration of the
tracker's steady motion model (``class_acceleration_sigma`` times the smallest of
``model_acceleration_factors``: 1.25 m/s^2 for a car) and white turn-rate acceleration of
the class's acceleration over its turning radius (``class_turn_radius_m``: 1 rad/s^2 for a
car; an arc's turn rate changes that fast where a car enters or leaves it). It starts from
the tracker's estimate the first time a vehicle's views are refined, and again whenever a
view falls outside it by more than ``gate_sigmas`` (another vehicle took the track, or it
braked harder than the model expects). Only the reported position comes from it: the
tracker's filter, association, the motion rules and births are unchanged, so are ids. No
delay: each instant is reported from that instant's views and the ones before.
"""

from __future__ import annotations

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching.fusion.table import FusionContext, TrackTable

_STATE = 5  # x, y, speed, heading, turn rate

TURNING_CLASSES = ("car",)
"""The classes reported from the turning filter. The filter averages a vehicle's views over
time, so it helps where their errors are noise, not where one camera's view of the vehicle
is off by metres instant after instant: a bus's or a truck's box is placed by a class-typical
size that a real one misses by metres (at the simulated crossroads a stopped bus's views lay
2.3 m apart, one camera's with a sharp learned noise, and the filter settled on it: buses
0.65 -> 1.34 m off, bicycles 0.20 -> 0.23 m). Those keep each instant's correction."""


class TurnFilter:
    """A coordinated-turn filter per vehicle track, for the position it is reported at.

    Args:
        context: the tracker's configuration (per-class accelerations, turning radii, the
            steady motion model's factor, ``object_sigma_m``, ``gate_sigmas``).

    Example:
        >>> from cblrs.matching.fusion.config import FusionConfig
        >>> from cblrs.matching.fusion.noise import NoiseModel
        >>> context = FusionContext(FusionConfig(), ["a"], np.zeros((1, 2)),
        ...                         np.zeros(9), np.ones(9), NoiseModel(0.2, 0.01))
        >>> float(TurnFilter(context).acceleration[1])  # a car's, m/s^2
        1.25
    """

    def __init__(self, context: FusionContext):
        self.context = context
        config = context.config
        steady = min(config.model_acceleration_factors)
        accel = np.array(
            [
                config.class_acceleration_sigma.get(name, config.acceleration_sigma)
                for name in CLASS_NAMES
            ]
            + [config.acceleration_sigma]
        )
        self.acceleration = steady * accel
        # Turn-rate acceleration: the class's acceleration over its turning radius (zero
        # for classes that turn on the spot; they are not vehicles and never filtered).
        radius = context.class_turn_radius
        self.classes = np.array([name in TURNING_CLASSES for name in CLASS_NAMES] + [False])
        self.turn_acceleration = np.where(np.isfinite(radius), accel / radius, 0.0)

    def applies(self, class_id: np.ndarray) -> np.ndarray:
        """(K,) bool: the tracks of these classes are reported from their turning filter."""
        return self.classes[FusionContext.class_slot(class_id)]

    def locate(
        self,
        tracks: TrackTable,
        rows: np.ndarray,
        fused_xy: np.ndarray,
        fused_covariance: np.ndarray,
        timestamp: float,
    ) -> np.ndarray:
        """(K, 2) where the tracks ``rows`` are reported, updating their turning filters.

        Args:
            tracks: the tracks, predicted to ``timestamp`` and not yet updated (a filter
                starts from this estimate); their ``turn_state``, ``turn_covariance`` and
                ``turn_time`` are updated in place.
            rows: (K,) the tracks with refined views at this instant.
            fused_xy: (K, 2) their views fused, metres.
            fused_covariance: (K, 2, 2) that fusion's covariance, square metres.
            timestamp: the window's time, seconds.
        """
        if not len(rows):
            return np.zeros((0, 2))
        state = tracks.turn_state[rows].copy()
        covariance = tracks.turn_covariance[rows].copy()
        fresh = ~np.isfinite(state[:, 0])
        slot = FusionContext.class_slot(tracks.class_id[rows])
        dt = np.where(fresh, 0.0, timestamp - tracks.turn_time[rows])
        state, covariance = self._predict(state, covariance, np.maximum(dt, 0.0), slot)
        noise = fused_covariance + self.context.object_covariance
        start_state, start_covariance = self._start(tracks, rows, slot)
        state[fresh], covariance[fresh] = start_state[fresh], start_covariance[fresh]
        innovation = fused_xy - state[:, :2]
        total = covariance[:, :2, :2] + noise
        whitened = np.linalg.solve(total, innovation[..., None])[..., 0]
        distance = np.einsum("ki,ki->k", innovation, whitened)
        # A view the filter cannot explain: start again from the tracker's estimate.
        lost = ~fresh & (distance > self.context.config.gate_sigmas**2)
        state[lost], covariance[lost] = start_state[lost], start_covariance[lost]
        innovation = fused_xy - state[:, :2]
        total = covariance[:, :2, :2] + noise
        gain = covariance[:, :, :2] @ np.linalg.inv(total)
        state = state + np.einsum("kij,kj->ki", gain, innovation)
        covariance = covariance - gain @ covariance[:, :2, :]
        covariance = 0.5 * (covariance + np.swapaxes(covariance, 1, 2))
        tracks.turn_state[rows] = state
        tracks.turn_covariance[rows] = covariance
        tracks.turn_time[rows] = timestamp
        return state[:, :2].copy()

    def _start(
        self, tracks: TrackTable, rows: np.ndarray, slot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tracker's estimate of ``rows`` as turning states: speed and heading from its
        velocity, turn rate 0 within what the speed and turning radius allow."""
        position = tracks.state[rows, :2]
        velocity = tracks.state[rows, 2:4]
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        heading = np.arctan2(velocity[:, 1], velocity[:, 0])
        velocity_variance = np.trace(tracks.covariance[rows, 2:4, 2:4], axis1=1, axis2=2)
        radius = self.context.class_turn_radius[slot]
        state = np.zeros((len(rows), _STATE))
        state[:, :2] = position
        state[:, 2] = speed
        state[:, 3] = heading
        covariance = np.zeros((len(rows), _STATE, _STATE))
        covariance[:, :2, :2] = tracks.covariance[rows, :2, :2]
        covariance[:, 2, 2] = velocity_variance
        covariance[:, 3, 3] = np.minimum(velocity_variance / np.maximum(speed, 0.5) ** 2, np.pi**2)
        covariance[:, 4, 4] = (np.maximum(speed, 0.5) / radius) ** 2
        return state, covariance

    def _predict(
        self, state: np.ndarray, covariance: np.ndarray, dt: np.ndarray, slot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Move each state along its arc by its own ``dt`` (the chord of the arc: length
        ``speed dt sinc(turn dt / 2)``, direction ``heading + turn dt / 2``)."""
        speed, heading, turn = state[:, 2], state[:, 3], state[:, 4]
        half = 0.5 * turn * dt
        ratio = np.sinc(half / np.pi)  # sin(half) / half
        # d ratio / d half: (half cos half - sin half) / half^2, -half / 3 near 0.
        small = np.abs(half) < 1e-4
        safe = np.where(small, 1.0, half)
        slope = np.where(small, -half / 3.0, (safe * np.cos(safe) - np.sin(safe)) / safe**2)
        chord = speed * dt * ratio
        direction = heading + half
        cos, sin = np.cos(direction), np.sin(direction)
        moved = state.copy()
        moved[:, 0] += chord * cos
        moved[:, 1] += chord * sin
        moved[:, 3] += turn * dt
        jacobian = np.tile(np.eye(_STATE), (len(state), 1, 1))
        jacobian[:, 0, 2] = dt * ratio * cos
        jacobian[:, 1, 2] = dt * ratio * sin
        jacobian[:, 0, 3] = -chord * sin
        jacobian[:, 1, 3] = chord * cos
        d_chord = speed * dt * slope * 0.5 * dt
        jacobian[:, 0, 4] = d_chord * cos - chord * sin * 0.5 * dt
        jacobian[:, 1, 4] = d_chord * sin + chord * cos * 0.5 * dt
        jacobian[:, 3, 4] = dt
        # White longitudinal and turn-rate accelerations.
        effect = np.zeros((len(state), _STATE, 2))
        effect[:, 0, 0] = 0.5 * dt**2 * np.cos(heading)
        effect[:, 1, 0] = 0.5 * dt**2 * np.sin(heading)
        effect[:, 2, 0] = dt
        effect[:, 3, 1] = 0.5 * dt**2
        effect[:, 4, 1] = dt
        spectral = np.zeros((len(state), 2, 2))
        spectral[:, 0, 0] = self.acceleration[slot] ** 2
        spectral[:, 1, 1] = self.turn_acceleration[slot] ** 2
        process = effect @ spectral @ np.swapaxes(effect, 1, 2)
        covariance = jacobian @ covariance @ np.swapaxes(jacobian, 1, 2) + process
        return moved, covariance
