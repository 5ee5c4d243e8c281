"""Cameras and planes shared by the core tests (imported as a plain module)."""

from __future__ import annotations

import numpy as np

from cblrs.calibration import WILDTRACK_GROUND
from cblrs.camera import Camera
from cblrs.plane import PlaneSpec


def wildtrack_plane(bits: int = 16) -> PlaneSpec:
    x0, y0, width, length = WILDTRACK_GROUND
    return PlaneSpec(1, (x0, y0), width, length, bits=bits, name="ground")


def posed_camera(distortion=None, size=(640, 360)) -> Camera:
    """A camera 6 m up at (0, -12), looking along +y, 12 degrees down (horizon at row ~73)."""
    return Camera.from_pose(
        "synthetic", (0.0, -12.0, 6.0), 90.0, 12.0, 500.0, size, distortion=distortion
    )


STRONG_LENS = np.array([-0.3, 0.08, 0.0, 0.0, 0.0])
