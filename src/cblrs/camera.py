"""Camera model: intrinsics, lens distortion, pose and ground-plane homographies.

Conventions:
    * World coordinates are metres, right-handed, z up; the ground is the plane z = 0.
      Heights (``height_m`` arguments, the third column of ``world_xyz``, ``centre[2]``)
      are always metres above the ground, on the camera's side.
    * Pixel coordinates follow OpenCV: x to the right, y down, the centre of pixel (i, j)
      at (i, j).
    * ``rotation`` and ``translation`` map world to camera: ``X_cam = R @ X_world + t``.
    * A homography ``H`` maps homogeneous world ``(x, y, 1)`` on a plane to homogeneous
      *undistorted* pixels.

A camera is either fully calibrated (``K``, distortion, ``R``, ``t``) or known only by its
ground homography (as in AI City 2024). The second kind can only map the plane z = 0 and
has no lens model.

A calibration whose world is left-handed as seen by the camera (every MultiviewX camera) is
turned into an equivalent proper-rotation description by :mod:`cblrs.handedness`; such a
camera records ``height_axis = -1``.

OpenCV is imported by the methods that call it (lens distortion, projections through a lens
model, RQ decomposition), not with this module: a WILDTRACK camera read from its files needs
none of them, and ``cblrs track`` then starts without loading OpenCV (40-80 ms of CPU and
some 30 MiB); the Rodrigues vector is converted by
:func:`cblrs.geometry.rotation_from_vector`, OpenCV's own arithmetic.

The rotations and ground-plane homographies the camera is built from are pure functions in
:mod:`cblrs.geometry`; the file readers are in :mod:`cblrs.calibration`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.errors import CalibrationError
from cblrs.geometry import (
    _as_points,
    homography_pixel_to_world,
    plane_homography,
    rotation_from_pose,
    rotation_from_vector,
)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# World points closer than this to the camera (in camera depth, metres) count as behind it.
_MIN_DEPTH_M = 1e-6


def _check_matrix(matrix: Any, shape: tuple[int, ...], name: str) -> FloatArray:
    array = np.asarray(matrix, dtype=np.float64)
    if array.shape != shape:
        raise CalibrationError(f"{name} must have shape {shape}, got {array.shape}.")
    if not np.all(np.isfinite(array)):
        raise CalibrationError(f"{name} contains NaN or infinite values.")
    return array


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera observing ground planes.

    Build one with :meth:`from_extrinsics`, :meth:`from_pose` or :meth:`from_homography`
    rather than directly.

    Attributes:
        name: camera identifier, unique within a scene.
        image_size: ``(width, height)`` in pixels.
        intrinsics: (3, 3) matrix K, or None for a homography-only camera.
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); empty if none.
        rotation: (3, 3) world-to-camera rotation, or None for a homography-only camera.
        translation: (3,) world-to-camera translation in metres, or None.
        homography: (3, 3) map from the ground plane z = 0 (metres) to undistorted pixels.
        height_axis: +1 when ``rotation``/``translation`` act on (x, y, height); -1 when
            they act on (x, y, -height), the proper-rotation form of a left-handed
            calibration (see :mod:`cblrs.handedness`). Methods take
            and return heights either way.
    """

    name: str
    image_size: tuple[int, int]
    homography: FloatArray
    intrinsics: FloatArray | None = None
    distortion: FloatArray = field(default_factory=lambda: np.zeros(0))
    rotation: FloatArray | None = None
    translation: FloatArray | None = None
    height_axis: int = 1

    def __post_init__(self) -> None:
        width, height = self.image_size
        if int(width) <= 0 or int(height) <= 0:
            raise CalibrationError(
                f"camera {self.name!r}: image size must be positive, got {self.image_size}."
            )
        object.__setattr__(self, "image_size", (int(width), int(height)))
        object.__setattr__(self, "homography", _check_matrix(self.homography, (3, 3), "homography"))
        if abs(np.linalg.det(self.homography)) < 1e-12:
            raise CalibrationError(f"camera {self.name!r}: the homography is singular.")
        distortion = np.asarray(self.distortion, dtype=np.float64).ravel()
        if not np.all(np.isfinite(distortion)):
            raise CalibrationError(f"camera {self.name!r}: distortion has NaN or inf values.")
        object.__setattr__(self, "distortion", distortion)
        has_pose = self.intrinsics is not None
        if has_pose != (self.rotation is not None) or has_pose != (self.translation is not None):
            raise CalibrationError(
                f"camera {self.name!r}: intrinsics, rotation and translation go together."
            )
        if self.intrinsics is not None:
            object.__setattr__(
                self, "intrinsics", _check_matrix(self.intrinsics, (3, 3), "intrinsics")
            )
            object.__setattr__(self, "rotation", _check_matrix(self.rotation, (3, 3), "rotation"))
            object.__setattr__(
                self, "translation", _check_matrix(self.translation, (3,), "translation")
            )
        elif np.any(distortion != 0):
            raise CalibrationError(
                f"camera {self.name!r}: lens distortion needs intrinsics; "
                "a homography-only camera has none."
            )
        if self.height_axis not in (1, -1):
            raise CalibrationError(
                f"camera {self.name!r}: height_axis must be 1 or -1, got {self.height_axis!r}."
            )
        object.__setattr__(self, "height_axis", int(self.height_axis))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_extrinsics(
        cls,
        name: str,
        intrinsics: NDArray,
        rotation: NDArray,
        translation: NDArray,
        image_size: tuple[int, int],
        distortion: NDArray | None = None,
        height_axis: int = 1,
    ) -> Camera:
        """Camera from K, a world-to-camera rotation (matrix or Rodrigues vector) and t, metres.

        The extrinsics are taken as given, whatever side of the camera the ground lies on;
        calibration readers pass the result through
        :func:`cblrs.handedness.orient_to_ground`.
        ``height_axis`` -1 says the world's third axis points down (see the class notes).
        """
        rotation = np.asarray(rotation, dtype=np.float64)
        if rotation.shape in ((3,), (3, 1), (1, 3)):
            rotation = rotation_from_vector(rotation)
        intrinsics = _check_matrix(intrinsics, (3, 3), "intrinsics")
        rotation = _check_matrix(rotation, (3, 3), "rotation")
        translation = _check_matrix(np.asarray(translation, dtype=np.float64).ravel(), (3,), "t")
        homography = plane_homography(intrinsics, rotation, translation, 0.0)
        return cls(
            name=name,
            image_size=image_size,
            homography=homography,
            intrinsics=intrinsics,
            distortion=np.zeros(0) if distortion is None else np.asarray(distortion).ravel(),
            rotation=rotation,
            translation=translation,
            height_axis=height_axis,
        )

    @classmethod
    def from_pose(
        cls,
        name: str,
        position: tuple[float, float, float],
        pan_deg: float,
        tilt_deg: float,
        focal_px: float,
        image_size: tuple[int, int],
        roll_deg: float = 0.0,
        distortion: NDArray | None = None,
    ) -> Camera:
        """Camera in the paper's form: position, three angles, focal length, image size.

        Args:
            position: camera centre (x, y, z) in metres; z is the height above the ground.
            pan_deg, tilt_deg, roll_deg: see :func:`rotation_from_pose`.
            focal_px: focal length in pixels (square pixels, principal point at the centre).
            image_size: (width, height) in pixels.
        """
        width, height = image_size
        intrinsics = np.array(
            [[focal_px, 0.0, (width - 1) / 2.0], [0.0, focal_px, (height - 1) / 2.0], [0, 0, 1]]
        )
        rotation = rotation_from_pose(pan_deg, tilt_deg, roll_deg)
        translation = -rotation @ np.asarray(position, dtype=np.float64)
        return cls.from_extrinsics(
            name, intrinsics, rotation, translation, image_size, distortion=distortion
        )

    @classmethod
    def from_homography(cls, name: str, homography: NDArray, image_size: tuple[int, int]) -> Camera:
        """Camera known only by its ground homography (world metres -> pixels).

        The sign of a homography is arbitrary; it is fixed here so that the bottom row of the
        image, which a ground-looking camera sees, lies in front of the camera.
        """
        homography = _check_matrix(homography, (3, 3), "homography")
        width, height = int(image_size[0]), int(image_size[1])
        try:
            inverse = np.linalg.inv(homography)
        except np.linalg.LinAlgError:
            raise CalibrationError(f"camera {name!r}: the homography is singular.") from None
        bottom = np.stack(
            [np.linspace(0, width - 1, 16), np.full(16, height - 1.0), np.ones(16)], axis=1
        )
        if np.median((bottom @ inverse.T)[:, 2]) < 0:
            homography = -homography
        return cls(name=name, image_size=(width, height), homography=homography)

    @classmethod
    def from_projection(
        cls,
        name: str,
        projection: NDArray,
        image_size: tuple[int, int],
        distortion: NDArray | None = None,
    ) -> Camera:
        """Camera from a 3x4 projection matrix ``P ~ K [R | t]`` (world metres -> pixels).

        ``P`` is defined up to a scale of either sign; the sign is fixed so that the focal
        lengths come out positive and R is a proper rotation.
        """
        projection = _check_matrix(projection, (3, 4), "projection matrix")
        if abs(np.linalg.det(projection[:, :3])) < 1e-12 * np.abs(projection).max() ** 3:
            raise CalibrationError(f"camera {name!r}: the projection matrix is singular.")
        # det(K R) > 0 for positive focal lengths and a proper rotation.
        if np.linalg.det(projection[:, :3]) < 0:
            projection = -projection
        import cv2  # lazy: see the module notes

        intrinsics, rotation = cv2.RQDecomp3x3(projection[:, :3])[1:3]
        # RQ is unique only up to the signs of K's diagonal; make them positive.
        signs = np.diag(np.sign(np.diag(intrinsics)))
        intrinsics, rotation = intrinsics @ signs, signs @ rotation
        # P = K [R | t] with the scale of P carried by K, so t = K^-1 p4 is already in metres.
        translation = np.linalg.solve(intrinsics, projection[:, 3])
        return cls.from_extrinsics(
            name,
            intrinsics / intrinsics[2, 2],
            rotation,
            translation,
            image_size,
            distortion=distortion,
        )

    # ------------------------------------------------------------------ properties
    @property
    def has_pose(self) -> bool:
        """True when K, R and t are known (the camera can map planes at any height)."""
        return self.intrinsics is not None

    @property
    def has_distortion(self) -> bool:
        """Whether any lens distortion coefficient is non-zero."""
        return bool(np.any(self.distortion != 0))

    @property
    def field_radius(self) -> float:
        """Largest normalised radius (``hypot(x/z, y/z)``) the lens model images one-to-one.

        A polynomial lens model is only a lens within the field it was fitted on: past the
        radius where its radial map ``r -> r * radial(r)`` stops growing, it folds back and
        would put points seen at wider angles onto pixels that already image nearer ones (a
        real lens shows nothing there; :meth:`undistort_pixels` gives such pixels no
        position). Infinite without distortion or when the map keeps growing (searched up
        to a radius of 20, about 87 degrees off axis). Tangential terms are ignored.
        """
        cached = self.__dict__.get("_field_radius")
        if cached is None:
            cached = _field_radius(self.distortion)
            # A pure function of this frozen camera; cached on the instance.
            object.__setattr__(self, "_field_radius", cached)
        return cached

    def in_field(self, world_xyz: NDArray) -> BoolArray:
        """(N,) bool: world points (N, 3) in front of the camera and within its lens's field
        (:attr:`field_radius`); needs a posed camera."""
        camera_xyz = self.to_camera_frame(world_xyz)
        depth = camera_xyz[:, 2]
        front = depth > _MIN_DEPTH_M
        if not np.isfinite(self.field_radius):
            return front
        with np.errstate(divide="ignore", invalid="ignore"):
            radius = np.hypot(camera_xyz[:, 0], camera_xyz[:, 1]) / depth
        return front & (radius < self.field_radius)

    @property
    def centre(self) -> FloatArray:
        """Camera centre (x, y, height) in world metres (3,); needs a posed camera."""
        rotation, translation = self._pose()
        centre = -rotation.T @ translation
        centre[2] *= self.height_axis
        return centre

    def to_camera_frame(self, world_xyz: NDArray) -> FloatArray:
        """Camera coordinates (N, 3) of world points (N, 3) = (x, y, height) in metres.

        The third column is the depth along the optical axis (positive in front).
        """
        rotation, translation = self._pose()
        world_xyz = np.asarray(world_xyz, dtype=np.float64)
        if world_xyz.ndim != 2 or world_xyz.shape[1] != 3:
            raise ValueError(f"world_xyz must have shape (N, 3), got {world_xyz.shape}")
        if self.height_axis != 1:
            world_xyz = world_xyz * np.array([1.0, 1.0, self.height_axis])
        return world_xyz @ rotation.T + translation

    def _pose(self) -> tuple[FloatArray, FloatArray]:
        if self.rotation is None or self.translation is None:
            raise CalibrationError(
                f"camera {self.name!r} is known only by a homography; this needs K, R and t."
            )
        return self.rotation, self.translation

    def plane_homography(self, height_m: float = 0.0) -> FloatArray:
        """Homography from the horizontal plane z = ``height_m`` to undistorted pixels."""
        if height_m == 0.0:
            return self.homography
        rotation, translation = self._pose()
        assert self.intrinsics is not None
        return plane_homography(
            self.intrinsics, rotation, translation, self.height_axis * height_m
        )

    # ------------------------------------------------------------------ distortion
    def undistort_pixels(self, pixels: NDArray) -> FloatArray:
        """Map raw (distorted) pixels to ideal pinhole pixels, shape (N, 2).

        Strong lens models fold over near the image corners, where a raw pixel has no
        unique ideal position; such pixels (whose round trip misses by more than
        0.05 pixel) come back as NaN rather than as a wrong position.
        """
        pixels = _as_points(pixels, "pixels")
        if not self.has_distortion or len(pixels) == 0:
            return pixels.copy()
        assert self.intrinsics is not None
        import cv2  # lazy: see the module notes

        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)
        finite = np.isfinite(pixels).all(axis=1)
        undistorted = np.full_like(pixels, np.nan)
        if finite.any():
            undistorted[finite] = cv2.undistortPoints(
                pixels[finite].reshape(-1, 1, 2),
                self.intrinsics,
                self.distortion,
                R=np.eye(3),
                P=self.intrinsics,
                criteria=criteria,
            ).reshape(-1, 2)
            round_trip = self.distort_pixels(undistorted[finite])
            miss = np.hypot(*(round_trip - pixels[finite]).T) > 0.05
            rows = np.flatnonzero(finite)[miss]
            undistorted[rows] = np.nan
        return undistorted

    def distort_pixels(self, pixels: NDArray) -> FloatArray:
        """Map ideal pinhole pixels to raw (distorted) pixels, shape (N, 2)."""
        pixels = _as_points(pixels, "pixels")
        if not self.has_distortion or len(pixels) == 0:
            return pixels.copy()
        assert self.intrinsics is not None
        inverse_k = np.linalg.inv(self.intrinsics)
        normalised = np.column_stack([pixels, np.ones(len(pixels))]) @ inverse_k.T
        rays = normalised.reshape(-1, 1, 3)
        import cv2  # lazy: see the module notes

        projected, _ = cv2.projectPoints(
            rays, np.zeros(3), np.zeros(3), self.intrinsics, self.distortion
        )
        return projected.reshape(-1, 2).astype(np.float64)

    # ------------------------------------------------------------------ projections
    def pixel_to_world(
        self, pixels: NDArray, height_m: float = 0.0
    ) -> tuple[FloatArray, BoolArray]:
        """Intersect the rays through raw pixels with the plane z = ``height_m``.

        Args:
            pixels: (N, 2) raw image coordinates (distorted if the camera has distortion).
            height_m: plane height in metres.

        Returns:
            ``(world_xy, valid)``: (N, 2) metres and (N,) bool. A pixel is invalid when its
            ray does not meet the plane in front of the camera (above the horizon); its
            ``world_xy`` is NaN.

        Example:
            >>> camera = Camera.from_pose("c", (0, 0, 10), 0, 45, 1000, (1920, 1080))
            >>> world_xy, valid = camera.pixel_to_world([[959.5, 539.5]])
            >>> bool(valid[0]), world_xy.round(3).tolist()
            (True, [[10.0, 0.0]])
        """
        undistorted = self.undistort_pixels(pixels)
        return homography_pixel_to_world(self.plane_homography(height_m), undistorted)

    def world_to_pixel(
        self, world_xy: NDArray, height_m: float = 0.0
    ) -> tuple[FloatArray, BoolArray]:
        """Project ground points (metres) at height ``height_m`` to raw pixels.

        Returns:
            ``(pixels, valid)``: (N, 2) raw pixel coordinates and (N,) bool, False for points
            behind the camera. Points in front but outside the image are valid; compare with
            :meth:`contains` to know whether they are seen.
        """
        world_xy = _as_points(world_xy, "world_xy")
        homography = self.plane_homography(height_m)
        homogeneous = np.column_stack([world_xy, np.ones(len(world_xy))]) @ homography.T
        depth = homogeneous[:, 2]
        valid = depth > _MIN_DEPTH_M
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = homogeneous[:, :2] / depth[:, None]
        pixels[~valid] = np.nan
        if self.has_distortion and valid.any():
            pixels[valid] = self.distort_pixels(pixels[valid])
        return pixels, valid

    def project_points(self, world_xyz: NDArray) -> tuple[FloatArray, BoolArray]:
        """Project 3D world points (N, 3) = (x, y, height) metres to raw pixels.

        Needs a posed camera. Returns ``(pixels, valid)`` like :meth:`world_to_pixel`.
        """
        camera_xyz = self.to_camera_frame(world_xyz)
        assert self.intrinsics is not None
        valid = camera_xyz[:, 2] > _MIN_DEPTH_M
        pixels = np.full((len(world_xyz), 2), np.nan)
        if valid.any():
            import cv2  # lazy: see the module notes

            projected, _ = cv2.projectPoints(
                camera_xyz[valid].reshape(-1, 1, 3),
                np.zeros(3),
                np.zeros(3),
                self.intrinsics,
                self.distortion if self.has_distortion else None,
            )
            pixels[valid] = projected.reshape(-1, 2)
        return pixels, valid

    def contains(self, pixels: NDArray) -> BoolArray:
        """True for pixels inside the image (pixel centres 0..size-1, with half a pixel margin)."""
        pixels = _as_points(pixels, "pixels")
        width, height = self.image_size
        with np.errstate(invalid="ignore"):
            return (
                (pixels[:, 0] >= -0.5)
                & (pixels[:, 0] < width - 0.5)
                & (pixels[:, 1] >= -0.5)
                & (pixels[:, 1] < height - 0.5)
            )

    def undistorted_grid(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Ideal pinhole coordinates of every raw pixel, as two (H, W) float32 maps.

        Without distortion this is the pixel grid itself. With distortion the exact inverse
        is computed on a coarse grid (every 8 pixels), interpolated bilinearly and then
        polished by one Newton step of the lens model, which leaves about 1e-4 pixel of
        error (float32 resolution) except right at fold-overs. Pixels without a unique ideal
        position are NaN. The maps are computed once per camera and returned read-only.
        """
        cached = self.__dict__.get("_undistorted_grid")
        if cached is None:
            cached = self._compute_undistorted_grid()
            for grid in cached:
                grid.flags.writeable = False
            # A pure function of this frozen camera; cached on the instance.
            object.__setattr__(self, "_undistorted_grid", cached)
        return cached

    def _compute_undistorted_grid(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        width, height = self.image_size
        if not self.has_distortion:
            map_x, map_y = np.meshgrid(
                np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32)
            )
            return map_x, map_y
        # Exact inverse on a coarse grid (every `step` pixels, padded by two samples), then
        # a bilinear resize (exact float weights; OpenCV's bicubic kernel, a = -0.75, does
        # not even reproduce a linear field). The grid is placed so resize's pixel-centre
        # convention lands sample k on pixel step*k + offset.
        step, pad = 8, 2
        columns = -(-width // step) + 2 * pad
        rows = -(-height // step) + 2 * pad
        coarse_x = step * (np.arange(columns) - pad) + (step - 1) / 2.0
        coarse_y = step * (np.arange(rows) - pad) + (step - 1) / 2.0
        grid_x, grid_y = np.meshgrid(coarse_x, coarse_y)
        coarse = self.undistort_pixels(np.column_stack([grid_x.ravel(), grid_y.ravel()]))
        coarse = coarse.reshape(rows, columns, 2).astype(np.float32)
        import cv2  # lazy: see the module notes

        fine = cv2.resize(coarse, (columns * step, rows * step), interpolation=cv2.INTER_LINEAR)[
            pad * step : pad * step + height, pad * step : pad * step + width
        ]
        map_x, map_y = np.ascontiguousarray(fine[..., 0]), np.ascontiguousarray(fine[..., 1])
        if self.distortion.size in (4, 5, 8):
            map_x, map_y = self._newton_step(map_x, map_y)
        return map_x, map_y

    def _newton_step(
        self, map_x: NDArray[np.float32], map_y: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """One Newton step u <- u - (dD/du)^-1 (D(u) - p) on the whole grid.

        The bilinear maps are off by up to a few hundredths of a pixel where the lens bends
        strongly, which a 16-bit plane far away turns into several quantisation steps. The
        inverse Jacobian (dD/du)^-1 is the derivative of the map itself, taken by forward
        differences; it only needs to be roughly right for the step to converge.
        """
        height, width = map_x.shape
        distorted_x, distorted_y = self._distort_maps(map_x, map_y)
        distorted_x -= np.arange(width, dtype=np.float32)[None, :]  # residual D(u) - p
        distorted_y -= np.arange(height, dtype=np.float32)[:, None]
        derivative = np.empty_like(map_x)
        # d map / d column
        np.subtract(map_x[:, 1:], map_x[:, :-1], out=derivative[:, :-1])
        derivative[:, -1] = derivative[:, -2]
        correction_x = derivative * distorted_x
        np.subtract(map_y[:, 1:], map_y[:, :-1], out=derivative[:, :-1])
        derivative[:, -1] = derivative[:, -2]
        correction_y = derivative * distorted_x
        # d map / d row
        np.subtract(map_x[1:], map_x[:-1], out=derivative[:-1])
        derivative[-1] = derivative[-2]
        correction_x += derivative * distorted_y
        np.subtract(map_y[1:], map_y[:-1], out=derivative[:-1])
        derivative[-1] = derivative[-2]
        correction_y += derivative * distorted_y
        return map_x - correction_x, map_y - correction_y

    def _distort_maps(
        self, map_x: NDArray[np.float32], map_y: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """OpenCV's lens model (k1, k2, p1, p2[, k3[, k4, k5, k6]]) applied to (H, W) maps."""
        assert self.intrinsics is not None
        matrix = self.intrinsics.astype(np.float32)
        focal_x, skew, centre_x = matrix[0]
        focal_y, centre_y = matrix[1, 1], matrix[1, 2]
        coefficients = np.zeros(8, dtype=np.float32)
        coefficients[: self.distortion.size] = self.distortion
        k1, k2, p1, p2, k3, k4, k5, k6 = coefficients
        y = (map_y - centre_y) / focal_y
        x = (map_x - centre_x - skew * y) / focal_x
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if k4 or k5 or k6:
            radial /= 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        two_xy = 2 * x * y
        distorted_x = x * radial + p1 * two_xy + p2 * (r2 + 2 * x * x)
        distorted_y = y * radial + p1 * (r2 + 2 * y * y) + p2 * two_xy
        return (
            focal_x * distorted_x + skew * distorted_y + centre_x,
            focal_y * distorted_y + centre_y,
        )

    def __repr__(self) -> str:
        kind = "posed" if self.has_pose else "homography-only"
        lens = ", distorted" if self.has_distortion else ""
        mirrored = ", height axis mirrored" if self.height_axis == -1 else ""
        return (
            f"Camera({self.name!r}, {self.image_size[0]}x{self.image_size[1]}, "
            f"{kind}{lens}{mirrored})"
        )


def _field_radius(distortion: FloatArray, largest: float = 20.0) -> float:
    """Where OpenCV's radial model ``r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4
    + k6 r^6)`` first stops increasing (normalised radius; inf if it does not by ``largest``)."""
    coefficients = np.zeros(8)
    coefficients[: min(distortion.size, 8)] = distortion[:8]
    k1, k2, _, _, k3, k4, k5, k6 = coefficients
    if not (k1 or k2 or k3):
        return math.inf
    radius = np.linspace(0.0, largest, 200_001)
    r2 = radius**2
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        mapped = radius * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (
            1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    falling = np.flatnonzero(~(np.diff(mapped) > 0))
    return math.inf if len(falling) == 0 else float(radius[falling[0]])
