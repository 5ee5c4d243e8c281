"""The 1080p camera the benchmarks measure: WILDTRACK CVLab1 when present, else a built-in one."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cblrs.calibration import WILDTRACK_GROUND, read_wildtrack_cameras
from cblrs.camera import Camera
from cblrs.errors import CalibrationError
from cblrs.plane import PlaneSpec

SYNTHETIC_GROUND = (-25.0, 0.0, 50.0, 50.0)
"""Ground area (x0, y0, width, length) in metres seen by the built-in camera."""

# A mild barrel distortion (OpenCV k1, k2, p1, p2, k3) for the built-in camera's distorted
# variant, of the size of WILDTRACK's intrinsic_original coefficients.
SYNTHETIC_DISTORTION = np.array([-0.25, 0.06, 0.0, 0.0, 0.0])


@dataclass(frozen=True)
class BenchCamera:
    """A camera, the ground area its reference covers, and where it came from."""

    camera: Camera
    ground: tuple[float, float, float, float]
    source: str

    def plane(self, bits: int) -> PlaneSpec:
        x0, y0, width, length = self.ground
        return PlaneSpec(1, (x0, y0), width, length, bits=bits, name="ground")


def find_wildtrack(explicit: str | Path | None = None) -> Path | None:
    """The WILDTRACK folder: ``explicit``, ``$CBLRS_WILDTRACK``, or ``../shared/data/wildtrack``.

    The relative default is tried from the working directory and from the source checkout.
    """
    if explicit is not None:
        return Path(explicit) if (Path(explicit) / "calibrations").is_dir() else None
    here = Path(__file__).resolve()
    candidates = [
        os.environ.get("CBLRS_WILDTRACK"),
        Path.cwd().parent / "shared/data/wildtrack",
        here.parents[3].parent / "shared/data/wildtrack",
    ]
    for candidate in candidates:
        if candidate and (Path(candidate) / "calibrations").is_dir():
            return Path(candidate)
    return None


def synthetic_camera(distorted: bool = False) -> Camera:
    """A 1920x1080 camera 10 m up, 30 degrees down, looking along +y over the synthetic ground."""
    return Camera.from_pose(
        "synthetic-distorted" if distorted else "synthetic",
        position=(0.0, -8.0, 10.0),
        pan_deg=90.0,
        tilt_deg=30.0,
        focal_px=1400.0,
        image_size=(1920, 1080),
        distortion=SYNTHETIC_DISTORTION if distorted else None,
    )


def benchmark_camera(calibration: str | Path | None = None, distorted: bool = False) -> BenchCamera:
    """WILDTRACK CVLab1 (metres) if the data set is found, else :func:`synthetic_camera`.

    Args:
        calibration: WILDTRACK folder; None looks in the default places.
        distorted: use the lens-distortion calibration (raw video frames).
    """
    root = find_wildtrack(calibration)
    if root is None:
        if calibration is not None:

            raise CalibrationError(f"{calibration} is not a WILDTRACK folder (no calibrations/).")
        return BenchCamera(synthetic_camera(distorted), SYNTHETIC_GROUND, "built-in synthetic")
    camera = read_wildtrack_cameras(root, distorted=distorted)[0]
    return BenchCamera(camera, WILDTRACK_GROUND, f"WILDTRACK {camera.name} ({root})")
