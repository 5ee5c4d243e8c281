"""The learned measurement-noise model of the fusion tracker (step 1 of its update).

Noise is ``a**2 + (b * d)**2`` along the camera's ray and ``e**2 + (c * d)**2`` across it
(``d`` the distance from the camera); :class:`NoiseModel` re-estimates the coefficients and an
along-ray bias online from how much the cameras that see one object disagree.
"""

from __future__ import annotations

import numpy as np

from cblrs.matching.fusion.gaussian import (
    inverse_cholesky_2x2,
    ray_covariance,
)
from cblrs.matching.solvers import nnls

_IDENTITY = np.eye(2)[None]  # read only


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

    constant_share = 0.04
    """Share of the views' squared disagreement a constant along-ray bias must explain,
    beyond the bias proportional to distance, to be used (``constant_bias``)."""

    def __init__(
        self, sigma_m: float, sigma_per_distance: float,
        lateral_per_distance: float | None = None, constant_bias: bool = False,
    ):
        lateral = sigma_per_distance if lateral_per_distance is None else lateral_per_distance
        self.prior = np.array([sigma_m**2, sigma_per_distance**2, sigma_m**2, lateral**2])
        self.constant_bias = constant_bias
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
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
        # A constant along-ray bias beside it (``constant_bias``), zero a priori (worth
        # prior_pairs pairs), and the sums its fit needs.
        self.constant_normal = self.prior_pairs
        self.constant_moment = 0.0
        self.bias_cross = 0.0
        self.difference_square = 0.0
        self.bias_constant_m = 0.0

    def bias(self, distance: np.ndarray, along_distance: np.ndarray | None = None) -> np.ndarray:
        """(N,) mean error along the ray (metres, positive: beyond the object) at (N,) metres.

        A camera's foot points can all land a little too far or too near (box bottoms
        drawn below or above the feet, a footprint whose near edge is the box bottom); a
        box edge off by a fixed fraction of the box height moves the point along the ground
        in proportion to ``along_distance`` (distance / camera height), as the noise does.
        Cameras looking from different sides disagree by it, so it is learned like the noise.
        """
        along_distance = distance if along_distance is None else along_distance
        return self.bias_constant_m + self.bias_per_distance * along_distance

    def _learn_bias(
        self, world_xy: np.ndarray, distance: np.ndarray, along_distance: np.ndarray,
        direction: np.ndarray, first: np.ndarray, second: np.ndarray,
    ) -> np.ndarray:
        """Update the bias from pairs ``(first, second)``; return the corrected positions.

        The difference of two views of one object is ``q (g_1 - g_2)`` on average (``g =
        along_distance * u``, ``u`` the unit rays): a least-squares fit of ``q``.

        With ``constant_bias`` it is ``k (u_1 - u_2) + q (g_1 - g_2)``: a body's foot point
        (its box's bottom) is its footprint's near edge, short of the centre the ground truth
        marks by about half a body whatever the distance. ``k`` and ``q`` are fitted together
        and used when ``k`` is negative (short: the near edge) and explains at least
        :attr:`constant_share` of the squared disagreement beyond what ``q`` alone does;
        otherwise ``q`` alone, as without it. Where boxes are drawn around the person's
        centre (annotations), or a detector's noise swamps it, nothing changes.
        """
        del distance
        reach = along_distance[:, None] * direction
        feature = reach[first] - reach[second]
        difference = world_xy[first] - world_xy[second]
        decay = self.forget_per_pair ** len(first)
        self.bias_normal = decay * self.bias_normal + float(np.sum(feature**2))
        self.bias_moment = decay * self.bias_moment + float(np.sum(feature * difference))
        self.bias_per_distance = self.bias_moment / self.bias_normal
        if not self.constant_bias:
            return world_xy - self.bias_per_distance * reach
        turn = direction[first] - direction[second]
        self.constant_normal = decay * self.constant_normal + float(np.sum(turn**2))
        self.constant_moment = decay * self.constant_moment + float(np.sum(turn * difference))
        self.bias_cross = decay * self.bias_cross + float(np.sum(turn * feature))
        self.difference_square = decay * self.difference_square + float(np.sum(difference**2))
        normal = np.array([[self.constant_normal, self.bias_cross],
                           [self.bias_cross, self.bias_normal]])
        moment = np.array([self.constant_moment, self.bias_moment])
        constant, per_distance = np.linalg.solve(normal, moment)
        explained = float(moment @ (constant, per_distance)) - (
            self.bias_moment * self.bias_per_distance)
        self.bias_constant_m = 0.0
        if constant < 0 and explained > self.constant_share * self.difference_square:
            self.bias_constant_m, self.bias_per_distance = float(constant), float(per_distance)
        return world_xy - self.bias_constant_m * direction - self.bias_per_distance * reach

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
        identity = _IDENTITY
        parts = np.zeros((len(first), 4, 2, 2))
        for one in (first, second):
            ray = direction[one]
            outer = ray[:, :, None] * ray[:, None, :]
            squared = (distance[one] ** 2)[:, None, None]
            along_squared = (along_distance[one] ** 2)[:, None, None]
            if isotropic:
                outer = 0.5 * np.broadcast_to(identity, outer.shape)
            across = identity - outer
            parts[:, 0] += outer
            parts[:, 1] += along_squared * outer
            parts[:, 2] += across
            parts[:, 3] += squared * across
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
        shrink = np.ones(len(squared))
        far = squared > limit  # (so never 0: no division by zero to silence)
        shrink[far] = np.sqrt(limit / squared[far])
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
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "normal": self.normal.tolist(),
            "moment": self.moment.tolist(),
            "coefficients": self.coefficients.tolist(),
            "bias_normal": self.bias_normal,
            "bias_moment": self.bias_moment,
            "bias_per_distance": self.bias_per_distance,
            "constant": [self.constant_normal, self.constant_moment, self.bias_cross,
                         self.difference_square, self.bias_constant_m],
        }

    def set_state(self, state: dict) -> None:
        """Restore a state saved by :meth:`get_state`."""
        self.normal = np.asarray(state["normal"], np.float64).reshape(4, 4)
        self.moment = np.asarray(state["moment"], np.float64).reshape(4)
        self.coefficients = np.asarray(state["coefficients"], np.float64).reshape(4)
        self.bias_normal = float(state["bias_normal"])
        self.bias_moment = float(state["bias_moment"])
        self.bias_per_distance = float(state["bias_per_distance"])
        # (a state saved before the constant bias: none learnt yet)
        constant = state.get("constant", [self.prior_pairs, 0.0, 0.0, 0.0, 0.0])
        (self.constant_normal, self.constant_moment, self.bias_cross,
         self.difference_square, self.bias_constant_m) = (float(value) for value in constant)
