"""Clicked points with errors on both sides: the noise model and the least-squares refinement.

A clicked correspondence is wrong in two ways: the click misses the pixel by a pixel or two
(``click_px``), and the ground position is known only so well (a site plan's accuracy, the
spot on the map that "is" the feature in the frame: ``ground_m``). Near the camera a metre of
ground spans hundreds of pixels, far away a few: the same ground error is 30 px for a point at
the bottom of the frame and 1 px near the horizon. Fitting pixel errors alone lets the near
points, whose pixel errors are large but whose ground errors are small, pull the fit away
from the far points, which is where most of a scene's ground lies.

So every model is refined by maximum likelihood under both errors (errors in variables, as a
surveyor adjusts ground control points with their stated accuracy): the unknowns are the
model's parameters and the true ground position of each point, and the cost is

    sum_i |project(theta, X_i) - u_i|^2 / click_px^2 + |X_i - x_i|^2 / ground_m^2

(``u_i``, ``x_i`` the clicked pixel and ground position; ``scipy.optimize.least_squares``,
sparse Jacobian). A point's disagreement with a model is its Mahalanobis distance under
``Sigma_i = click_px^2 I + ground_m^2 J_i J_i^T`` (``J_i``: pixels per metre at the point),
which is what outlier tests and cross-validation compare.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera

FloatArray = NDArray[np.float64]

# Model names as in cblrs.calibrate.fit.Model (plain strings here to keep this module free of
# the fit's types).
HOMOGRAPHY, POSE, FOCAL, K1 = "homography", "pose", "focal", "k1"
PARAMETERS = {HOMOGRAPHY: 8, POSE: 6, FOCAL: 7, K1: 8}


@dataclass(frozen=True)
class PointNoise:
    """How wrong a clicked point may be (one standard deviation).

    Attributes:
        click_px: of the clicked pixel, per image axis, pixels.
        ground_m: of the ground position, per ground axis, metres.
    """

    click_px: float = 2.0
    ground_m: float = 0.1


@dataclass(frozen=True, eq=False)
class Parameterisation:
    """One model's parameters <-> a camera, and the projection world -> pixels it implies.

    Homography: 8 entries of the homography between Hartley-normalised world and image
    coordinates (its last entry fixed to 1: the points' centroid is seen, so it is not 0).
    Pose models: Rodrigues vector (3), translation (3, metres), then the focal length (focal,
    k1; pixels) and k1; the principal point is the image centre and pixels are square.
    """

    model: str
    image_size: tuple[int, int]
    focal_px: float | None = None  # the fixed focal length of model pose
    world_norm: FloatArray | None = None
    image_norm: FloatArray | None = None

    @property
    def size(self) -> int:
        return PARAMETERS[self.model]

    @property
    def principal_point(self) -> FloatArray:
        width, height = self.image_size
        return np.array([(width - 1) / 2.0, (height - 1) / 2.0])

    def homography(self, params: FloatArray) -> FloatArray:
        """World metres -> pixels (3, 3) of a homography parameter vector."""
        assert self.world_norm is not None and self.image_norm is not None
        normalised = np.append(params, 1.0).reshape(3, 3)
        return np.asarray(
            np.linalg.solve(self.image_norm, normalised @ self.world_norm), dtype=np.float64
        )

    def project(self, params: FloatArray, world_xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(pixels (N, 2), depth (N,))``; depth > 0 in front of the camera."""
        world_xy = np.asarray(world_xy, dtype=np.float64)
        if self.model == HOMOGRAPHY:
            homogeneous = (
                np.column_stack([world_xy, np.ones(len(world_xy))]) @ self.homography(params).T
            )
            depth = homogeneous[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                return homogeneous[:, :2] / depth[:, None], depth
        rotation = cv2.Rodrigues(np.asarray(params[:3], dtype=np.float64))[0]
        camera_xyz = world_xy @ rotation[:, :2].T + params[3:6]
        depth = camera_xyz[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            normalised = camera_xyz[:, :2] / depth[:, None]
        focal = self.focal(params)
        if self.model == K1:
            normalised = normalised * (1.0 + params[7] * np.sum(normalised**2, axis=1))[:, None]
        return focal * normalised + self.principal_point, depth

    def focal(self, params: FloatArray) -> float:
        """The focal length (pixels) of a pose model's parameters."""
        if self.model == POSE:
            assert self.focal_px is not None
            return float(self.focal_px)
        return float(params[6])

    def camera(self, params: FloatArray, name: str) -> Camera:
        if self.model == HOMOGRAPHY:
            return Camera.from_homography(name, self.homography(params), self.image_size)
        focal = self.focal(params)
        centre = self.principal_point
        intrinsics = np.array([[focal, 0, centre[0]], [0, focal, centre[1]], [0, 0, 1.0]])
        distortion = np.array([params[7], 0.0, 0.0, 0.0]) if self.model == K1 else np.zeros(0)
        return Camera.from_extrinsics(
            name,
            intrinsics,
            np.asarray(params[:3], dtype=np.float64),
            np.asarray(params[3:6], dtype=np.float64),
            self.image_size,
            distortion=distortion,
        )

    @classmethod
    def of_camera(
        cls, model: str, camera: Camera, world_xy: FloatArray, image_xy: FloatArray
    ) -> tuple[Parameterisation, FloatArray]:
        """The parameterisation of ``model`` and the parameters of ``camera`` in it.

        ``world_xy``/``image_xy`` set the homography's normalisation (any points of the fit).
        """
        size = camera.image_size
        if model == HOMOGRAPHY:
            world_norm, image_norm = normalising(world_xy), normalising(image_xy)
            matrix = image_norm @ camera.homography @ np.linalg.inv(world_norm)
            matrix = matrix / matrix[2, 2]
            return cls(model, size, world_norm=world_norm, image_norm=image_norm), matrix.ravel()[
                :8
            ].copy()
        assert camera.rotation is not None and camera.translation is not None
        assert camera.intrinsics is not None
        rvec = cv2.Rodrigues(camera.rotation)[0].ravel()
        params = [*rvec, *camera.translation]
        focal = float(camera.intrinsics[0, 0])
        if model in (FOCAL, K1):
            params.append(focal)
        if model == K1:
            params.append(float(camera.distortion[0]) if len(camera.distortion) else 0.0)
        return cls(model, size, focal_px=focal if model == POSE else None), np.array(params)


def normalising(points: FloatArray) -> FloatArray:
    """Hartley's normalisation (3, 3): centroid to 0, mean distance sqrt(2)."""
    centre = points.mean(axis=0)
    scale = math.sqrt(2) / max(float(np.mean(np.hypot(*(points - centre).T))), 1e-12)
    return np.array([[scale, 0, -scale * centre[0]], [0, scale, -scale * centre[1]], [0, 0, 1]])


@dataclass(frozen=True, eq=False)
class Refined:
    """A model refined by :func:`refine`.

    Attributes:
        parameterisation: the model's parameterisation.
        params: (k,) the fitted parameters.
        chi_square: the cost at the minimum (sum of squared normalised errors).
        redundancy: observations minus unknowns (``2 N - k``).
        jacobian: (4 N, k + 2 N) of the normalised errors at the minimum.
    """

    parameterisation: Parameterisation
    params: FloatArray
    chi_square: float
    redundancy: int
    jacobian: FloatArray

    def camera(self, name: str) -> Camera:
        return self.parameterisation.camera(self.params, name)

    @property
    def covariance(self) -> FloatArray:
        """(k, k) covariance of the parameters, the ground positions marginalised out;
        widened (never narrowed) when the errors exceed the stated noise."""
        size = self.parameterisation.size
        information = self.jacobian.T @ self.jacobian
        covariance = np.asarray(np.linalg.pinv(information)[:size, :size], dtype=np.float64)
        if self.redundancy > 0:
            covariance = covariance * max(1.0, self.chi_square / self.redundancy)
        return covariance


def refine(
    parameterisation: Parameterisation,
    params: FloatArray,
    image_xy: FloatArray,
    world_xy: FloatArray,
    noise: PointNoise,
    robust: bool = False,
) -> Refined:
    """Maximum-likelihood parameters of a model under click and ground errors (module notes).

    Args:
        parameterisation: the model.
        params: (k,) starting parameters (a linear or pixel-only fit).
        image_xy: (N, 2) clicked pixels.
        world_xy: (N, 2) their ground positions, metres.
        noise: the points' standard deviations.
        robust: limit the pull of gross errors (a soft L1 loss beyond twice the noise), for
            a fit that still contains outliers; ``chi_square`` is then the robust cost.
    """
    count, size = len(image_xy), parameterisation.size

    def residuals(unknowns: FloatArray) -> FloatArray:
        ground = unknowns[size:].reshape(count, 2)
        pixels, _ = parameterisation.project(unknowns[:size], ground)
        return np.concatenate(
            [
                ((pixels - image_xy) / noise.click_px).ravel(),
                ((ground - world_xy) / noise.ground_m).ravel(),
            ]
        )

    def jacobian(unknowns: FloatArray) -> FloatArray:
        # Point i's pixel residuals depend on the model and its own ground position only;
        # its ground residuals on its ground position only.
        params, ground = unknowns[:size], unknowns[size:].reshape(count, 2)
        matrix = np.zeros((4 * count, size + 2 * count))
        for column in range(size):
            step = 1e-6 * max(1.0, abs(float(params[column])))
            ahead, behind = params.copy(), params.copy()
            ahead[column] += step
            behind[column] -= step
            difference = (
                parameterisation.project(ahead, ground)[0]
                - parameterisation.project(behind, ground)[0]
            )
            matrix[: 2 * count, column] = (difference / (2 * step * noise.click_px)).ravel()
        local = pixels_per_metre(parameterisation, params, ground) / noise.click_px
        for index in range(count):
            columns = slice(size + 2 * index, size + 2 * index + 2)
            matrix[2 * index : 2 * index + 2, columns] = local[index]
            matrix[2 * count + 2 * index : 2 * count + 2 * index + 2, columns] = (
                np.eye(2) / noise.ground_m
            )
        return matrix

    # lazy: scipy.optimize takes ~0.4 s of CPU to import; a site or dashboard that fits no
    # points need not pay for it (see fit.py)
    from scipy.optimize import least_squares

    start = np.concatenate([np.asarray(params, dtype=np.float64), world_xy.ravel()])
    method = "lm" if 4 * count >= size + 2 * count and not robust else "trf"
    solution = least_squares(
        residuals,
        start,
        jac=jacobian,
        method=method,
        loss="soft_l1" if robust else "linear",
        f_scale=2.0,
        x_scale="jac",
        ftol=1e-10,
        xtol=1e-10,
        gtol=1e-10,
        max_nfev=100 * (size + 2 * count),
    )
    chi_square = float(2 * solution.cost)
    return Refined(
        parameterisation,
        solution.x[:size].copy(),
        chi_square,
        2 * count - size,
        np.asarray(solution.jac, dtype=np.float64),
    )


def pixels_per_metre(
    parameterisation: Parameterisation, params: FloatArray, world_xy: FloatArray
) -> FloatArray:
    """(N, 2, 2) Jacobian of pixels with respect to ground metres at each point."""
    step = 1e-4
    jacobian = np.empty((len(world_xy), 2, 2))
    for axis in range(2):
        offset = np.zeros(2)
        offset[axis] = step
        ahead, _ = parameterisation.project(params, world_xy + offset)
        behind, _ = parameterisation.project(params, world_xy - offset)
        jacobian[:, :, axis] = (ahead - behind) / (2 * step)
    return jacobian


def normalised_errors(
    parameterisation: Parameterisation,
    params: FloatArray,
    image_xy: FloatArray,
    world_xy: FloatArray,
    noise: PointNoise,
) -> FloatArray:
    """(N,) squared Mahalanobis distance of each clicked point from the model's prediction.

    ``inf`` for a point the model puts behind the camera. Under the stated noise a point
    that fits has a chi-square(2) value: 95 % below 6.0, 99.9 % below 13.8.
    """
    predicted, depth = parameterisation.project(params, world_xy)
    residual = predicted - image_xy
    jacobian = pixels_per_metre(parameterisation, params, world_xy)
    covariance = noise.click_px**2 * np.eye(2) + noise.ground_m**2 * (
        jacobian @ jacobian.transpose(0, 2, 1)
    )
    with np.errstate(invalid="ignore"):
        distance = np.einsum("ni,nij,nj->n", residual, np.linalg.inv(covariance), residual)
    distance[~(depth > 0) | ~np.isfinite(distance)] = np.inf
    return distance
