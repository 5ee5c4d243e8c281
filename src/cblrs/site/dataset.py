"""``cblrs site init``: a site file from a WILDTRACK, MultiviewX or AI City folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cblrs.calibration import MULTIVIEWX_GROUND, WILDTRACK_GROUND, calibration_layout, read_cameras
from cblrs.camera import Camera
from cblrs.datasets.multiview import GROUND_MARGIN_M as margin
from cblrs.plane import PlaneSpec
from cblrs.site.cameras import camera_entry, relative_path
from cblrs.site.schema import SITE_VERSION, SiteError

# How far past the cameras' bottom edge a plane estimated from AI City homographies reaches,
# metres from the seen ground's centre: beyond it a pixel covers too much ground to matter.
_MAX_REACH_M = 60.0


def site_from_dataset(
    dataset: str | Path,
    site_path: str | Path,
    inline: bool = False,
    plane: tuple[float, float, float, float] | None = None,
    bits: int = 16,
    name: str | None = None,
) -> dict[str, Any]:
    """The site document of a dataset folder.

    Args:
        dataset: a WILDTRACK or MultiviewX folder, or an AI City scene folder
            (``c*/calibration.json``).
        site_path: where the site file will be written (calibration references are made
            relative to its folder).
        inline: write the cameras' parameters into the file instead of referring to the
            dataset's calibration files.
        plane: ground plane ``(x0, y0, width, length)`` metres; default: the dataset's
            annotated area grown by the margin ``cblrs track`` uses (WILDTRACK, MultiviewX),
            or the ground the cameras see (AI City, estimated from their homographies).
        bits: bits per colour channel of the plane.
        name: the site's name (default: the folder's).

    Returns:
        The document (a mapping ready for :func:`cblrs.site.save_document`).
    """
    dataset = Path(dataset)
    layout = calibration_layout(dataset)
    if layout not in ("wildtrack", "multiviewx", "aicity") or not dataset.is_dir():
        raise SiteError(
            f"{dataset} is not a WILDTRACK, MultiviewX or AI City folder (no calibration files)."
        )
    cameras = read_cameras(dataset)
    folder = Path(site_path).parent
    entries = []
    for camera in cameras:
        if inline:
            entries.append(camera_entry(camera))
            continue
        if layout == "aicity":
            file = dataset / camera.name / "calibration.json"
            reference: Any = relative_path(file, folder)
        else:
            reference = {"file": relative_path(dataset, folder), "camera": camera.name}
        entries.append(
            {"name": camera.name, "image_size": list(camera.image_size), "calibration": reference}
        )
    if plane is None:
        plane = dataset_ground(layout, cameras)
    x0, y0, width, length = plane
    ground = PlaneSpec(1, (x0, y0), width, length, bits=bits, name="ground")
    return {
        "version": SITE_VERSION,
        "name": name or dataset.resolve().name,
        "planes": [
            {
                "id": ground.plane_id,
                "name": ground.name,
                "origin": list(ground.origin),
                "size": [ground.width, ground.length],
                "bits": ground.bits,
                "height": ground.height,
            }
        ],
        "cameras": entries,
    }


def dataset_ground(layout: str, cameras: list[Camera]) -> tuple[float, float, float, float]:
    """The ground plane ``cblrs track`` uses for a layout, or the ground AI City cameras see."""

    known = {"wildtrack": WILDTRACK_GROUND, "multiviewx": MULTIVIEWX_GROUND}.get(layout)
    if known is not None:
        x0, y0, width, length = known
        return (x0 - margin, y0 - margin, width + 2 * margin, length + 2 * margin)
    return seen_ground(cameras)


def seen_ground(cameras: list[Camera]) -> tuple[float, float, float, float]:
    """A rectangle (x0, y0, width, length) metres holding the ground the cameras see.

    Every camera's lower image half is sampled and projected onto the ground; points farther
    than ``_MAX_REACH_M`` from the median of what the camera sees are dropped (near the
    horizon a pixel spans metres), and the rectangle is rounded out to whole metres.
    """
    seen = []
    for camera in cameras:
        width, height = camera.image_size
        u, v = np.meshgrid(np.linspace(0, width - 1, 24), np.linspace(height / 2, height - 1, 12))
        world, valid = camera.pixel_to_world(np.column_stack([u.ravel(), v.ravel()]))
        world = world[valid]
        if len(world) == 0:
            continue
        centre = np.median(world, axis=0)
        seen.append(world[np.hypot(*(world - centre).T) <= _MAX_REACH_M])
    if not seen:
        raise SiteError(
            "the cameras see no ground, so the plane cannot be estimated; give it with --plane."
        )
    points = np.concatenate(seen)
    low = np.floor(np.percentile(points, 2, axis=0))
    high = np.ceil(np.percentile(points, 98, axis=0))
    width, length = max(high[0] - low[0], 1.0), max(high[1] - low[1], 1.0)
    return (float(low[0]), float(low[1]), float(width), float(length))
