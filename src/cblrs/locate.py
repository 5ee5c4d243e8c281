"""Localisers: pixel -> world position on the ground, three ways behind one interface.

* :class:`HomographyLocator` computes ``H^-1 p`` directly (the paper's baseline). It knows
  nothing of lens distortion.
* :class:`LUTLocator` reads a precomputed per-pixel table of world positions (float32).
* :class:`ColorLocator` reads the reference image and decodes the colour (the paper's method).

Each has a batched :meth:`locate` (vectorised over N pixels) and a one-point
:meth:`locate_one` (plain Python, as the paper timed it in Table I).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.errors import ReferenceImageError
from cblrs.geometry import MAX_WORLD_DISTANCE_M, homography_pixel_to_world
from cblrs.reference import ReferenceImage, nearest_pixel_indices

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@runtime_checkable
class Locator(Protocol):
    """Anything that maps pixels to ground positions."""

    image_size: tuple[int, int]

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """(N, 2) pixels -> ((N, 2) world metres, (N,) valid)."""
        ...

    def locate_one(self, x: float, y: float) -> tuple[float, float] | None:
        """One pixel -> (x, y) metres, or None when it sees no plane."""
        ...


class HomographyLocator:
    """Direct homography: ``world ~ H^-1 (x, y, 1)``.

    Args:
        homography: (3, 3) world (metres) -> undistorted pixel map, with the sign convention
            of :class:`cblrs.camera.Camera` (points in front have positive w).
        image_size: (width, height); pixels outside are invalid.
        bounds: optional ``(x0, y0, x1, y1)`` metres; positions outside are invalid, as for a
            reference image's plane.
    """

    def __init__(
        self,
        homography: NDArray,
        image_size: tuple[int, int],
        bounds: tuple[float, float, float, float] | None = None,
    ):
        self.homography = np.asarray(homography, dtype=np.float64)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.bounds = bounds
        inverse = np.linalg.inv(self.homography)
        self._inverse = inverse
        self._coefficients = tuple(float(value) for value in inverse.ravel())

    @classmethod
    def from_camera(cls, camera: Camera, height_m: float = 0.0, bounds=None) -> HomographyLocator:
        """The locator of a calibrated camera on the plane at ``height_m`` metres."""
        return cls(camera.plane_homography(height_m), camera.image_size, bounds)

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """(N, 2) world metres and a validity mask for (N, 2) pixels (batched)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        world_xy, valid = homography_pixel_to_world(self.homography, pixels)
        width, height = self.image_size
        with np.errstate(invalid="ignore"):
            valid &= (
                (pixels[:, 0] >= -0.5)
                & (pixels[:, 0] < width - 0.5)
                & (pixels[:, 1] >= -0.5)
                & (pixels[:, 1] < height - 0.5)
            )
            if self.bounds is not None:
                x0, y0, x1, y1 = self.bounds
                valid &= (
                    (world_xy[:, 0] >= x0)
                    & (world_xy[:, 0] <= x1)
                    & (world_xy[:, 1] >= y0)
                    & (world_xy[:, 1] <= y1)
                )
        world_xy[~valid] = np.nan
        return world_xy, valid

    def locate_one(self, x: float, y: float) -> tuple[float, float] | None:
        """World (x, y) of one pixel, or None where it sees no plane."""
        width, height = self.image_size
        if not (-0.5 <= x < width - 0.5 and -0.5 <= y < height - 0.5):
            return None
        a, b, c, d, e, f, g, h, i = self._coefficients
        scale = g * x + h * y + i
        if scale <= 0.0:
            return None
        world_x = (a * x + b * y + c) / scale
        world_y = (d * x + e * y + f) / scale
        if not (abs(world_x) <= MAX_WORLD_DISTANCE_M and abs(world_y) <= MAX_WORLD_DISTANCE_M):
            return None
        if self.bounds is not None:
            x0, y0, x1, y1 = self.bounds
            if not (x0 <= world_x <= x1 and y0 <= world_y <= y1):
                return None
        return world_x, world_y


class LUTLocator:
    """Per-pixel lookup table of world positions, float32 (H, W, 2), NaN where no plane.

    Build it from a camera (exact, including distortion) or by decoding a reference image.
    """

    def __init__(self, table: NDArray[np.float32]):
        table = np.asarray(table)
        if table.ndim != 3 or table.shape[2] != 2:
            raise ValueError(f"a LUT must have shape (H, W, 2), got {table.shape}")
        self.table = np.ascontiguousarray(table, dtype=np.float32)
        self.image_size = (self.table.shape[1], self.table.shape[0])
        self._flat = self.table.reshape(-1, 2)

    @classmethod
    def from_camera(
        cls,
        camera: Camera,
        height_m: float = 0.0,
        bounds: tuple[float, float, float, float] | None = None,
    ) -> LUTLocator:
        """Exact world position of every raw pixel centre (lens distortion included).

        Args:
            camera: the camera.
            height_m: plane height in metres.
            bounds: optional ``(x0, y0, x1, y1)`` metres; positions outside are NaN.
        """
        width, height = camera.image_size
        if camera.has_distortion:
            map_x, map_y = (grid.astype(np.float64) for grid in camera.undistorted_grid())
        else:  # separable grid: broadcast a row and a column
            map_x = np.arange(width, dtype=np.float64)[None, :]
            map_y = np.arange(height, dtype=np.float64)[:, None]
        inverse = np.linalg.inv(camera.plane_homography(height_m))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inverse_scale = 1.0 / (inverse[2, 0] * map_x + inverse[2, 1] * map_y + inverse[2, 2])
            world_x = (
                inverse[0, 0] * map_x + inverse[0, 1] * map_y + inverse[0, 2]
            ) * inverse_scale
            world_y = (
                inverse[1, 0] * map_x + inverse[1, 1] * map_y + inverse[1, 2]
            ) * inverse_scale
            # Same rule as homography_pixel_to_world: in front, not at the horizon.
            valid = (inverse_scale > 0) & (np.abs(world_x) <= MAX_WORLD_DISTANCE_M)
            valid &= np.abs(world_y) <= MAX_WORLD_DISTANCE_M
            if bounds is not None:
                x0, y0, x1, y1 = bounds
                valid &= (world_x >= x0) & (world_x <= x1) & (world_y >= y0) & (world_y <= y1)
        table = np.full((height, width, 2), np.nan, dtype=np.float32)
        np.copyto(table[..., 0], world_x, where=valid, casting="unsafe")
        np.copyto(table[..., 1], world_y, where=valid, casting="unsafe")
        return cls(table)

    @classmethod
    def from_reference(cls, reference: ReferenceImage) -> LUTLocator:
        """Decode every pixel of a reference image (cell centres; NaN where B = 0)."""
        width, height = reference.image_size
        pixels = reference.pixels
        table = np.full((height, width, 2), np.nan, dtype=np.float32)
        for plane in reference.planes:
            seen = pixels[..., 2] == plane.plane_id
            step_x, step_y = plane.step
            np.copyto(
                table[..., 0],
                plane.origin[0] + pixels[..., 0] * step_x,
                where=seen,
                casting="unsafe",
            )
            np.copyto(
                table[..., 1],
                plane.origin[1] + pixels[..., 1] * step_y,
                where=seen,
                casting="unsafe",
            )
        return cls(table)

    def save(self, path: str | Path) -> Path:
        """Write the table as a .npy file (what the paper's LUT costs on disk)."""
        path = Path(path)
        np.save(path, self.table)
        return path

    @classmethod
    def load(cls, path: str | Path) -> LUTLocator:
        """A lookup table saved with ``numpy.save``; ReferenceImageError if it cannot be read."""
        try:
            return cls(np.load(path, allow_pickle=False))
        except (OSError, ValueError) as error:
            raise ReferenceImageError(f"cannot read LUT {path}: {error}.") from None

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """(N, 2) world metres and a validity mask for (N, 2) pixels (batched)."""
        indices, inside = nearest_pixel_indices(pixels, self.image_size)
        world_xy = self._flat[indices].astype(np.float64)
        valid = inside & np.isfinite(world_xy[:, 0])
        world_xy[~valid] = np.nan
        return world_xy, valid

    def locate_one(self, x: float, y: float) -> tuple[float, float] | None:
        """World (x, y) of one pixel, or None where it sees no plane."""
        width, height = self.image_size
        # Written as one chained test so NaN (every comparison False) falls out too.
        if not (-0.5 <= x < width - 0.5 and -0.5 <= y < height - 0.5):
            return None
        column, row = int(x + 0.5), int(y + 0.5)
        world_x = self.table.item(row, column, 0)
        if world_x != world_x:  # NaN: no plane here
            return None
        return world_x, self.table.item(row, column, 1)


class ColorLocator:
    """The paper's method: read the reference colour at the pixel, decode it."""

    def __init__(self, reference: ReferenceImage):
        self.reference = reference
        self.image_size = reference.image_size
        self._packed = reference.packed
        # plane id -> (x0, y0, step_x, step_y) for the one-point path
        self._decoders = {
            plane.plane_id: (plane.origin[0], plane.origin[1], *plane.step)
            for plane in reference.planes
        }

    @classmethod
    def load(cls, path: str | Path, expected_size: tuple[int, int] | None = None) -> ColorLocator:
        """The locator of a reference PNG (see :func:`cblrs.reference.load_reference`)."""
        return cls(ReferenceImage.load(path, expected_size=expected_size))

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """(N, 2) world metres and a validity mask for (N, 2) pixels: their colours decoded."""
        return self.reference.locate(pixels)

    def locate_one(self, x: float, y: float) -> tuple[float, float] | None:
        """World (x, y) of one pixel from its colour, or None where B = 0 (no plane)."""
        width, height = self.image_size
        # Written as one chained test so NaN (every comparison False) falls out too.
        if not (-0.5 <= x < width - 0.5 and -0.5 <= y < height - 0.5):
            return None
        column, row = int(x + 0.5), int(y + 0.5)
        packed = self._packed.item(row * width + column)
        decoder = self._decoders.get(packed >> 32)
        if decoder is None:
            return None
        x0, y0, step_x, step_y = decoder
        return x0 + (packed & 0xFFFF) * step_x, y0 + ((packed >> 16) & 0xFFFF) * step_y
