"""The calibration page's backend: clicked pairs -> fit (live errors) -> site file -> reference.

The page shows a camera's frame beside the site map; the operator clicks a point in the
frame and the same point on the map, pair after pair. Each change of the pairs is fitted by
:func:`cblrs.calibrate.calibrate_camera` (:func:`fit_points`), and the page shows every
point's error (pixels and metres), the model the points allow and the RMS. Saving
(:func:`save_points`) writes the pairs into the site file as the camera's ``points`` (a
backup of the previous file is kept as ``<site>.bak``), reloads the site (so the file is
known to load), renders the camera's reference image from it and writes the reference PNG;
:func:`reference_preview` draws it over the frame with a metric grid.

Frames are never sent anywhere but to this page: a camera's frame comes from its ``frame:``
entry in the site file, from ``--frames DIR`` (``<camera>.png``/``.jpg``), or is opened in
the browser from a local file.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.calibrate import Correspondences, calibrate_camera
from cblrs.errors import CblrsError
from cblrs.reference import ReferenceImage
from cblrs.site import Site, backup_document, load_site, save_document
from cblrs.site.core import site_from_document
from cblrs.site.schema import read_document
from cblrs.viz.reference import reference_overlay

FRAME_SUFFIXES = (".png", ".jpg", ".jpeg")


class CalibrationPageError(CblrsError):
    """A request of the calibration page cannot be served (one sentence for the page)."""


def camera_list(site: Site, frames: Path | None) -> list[dict[str, Any]]:
    """Each camera's name, image size (if known), frame availability and stored points."""
    cameras = []
    for index, spec in enumerate(site.model.cameras):
        size = list(spec.image_size) if spec.image_size is not None else None
        if size is None:
            try:
                size = list(site.camera(spec.name).camera.image_size)
            except CblrsError:
                size = None
        points = [
            {"u": point.u, "v": point.v, "x": point.x, "y": point.y, "name": point.name}
            for point in (spec.points or [])
        ]
        cameras.append({
            "name": spec.name,
            "index": index,
            "image_size": size,
            "geometry": spec.geometry,
            "frame": frame_path(site, spec.name, frames) is not None,
            "points": points,
            "points_unit": spec.points_unit,
            "left_handed": spec.left_handed,
        })
    return cameras


def frame_path(site: Site, camera: str, frames: Path | None) -> Path | None:
    """The camera's frame image: ``frame:`` in the site file, else ``frames/<camera>.*``."""
    spec = site.model.cameras[site.index_of(camera)]
    if spec.frame is not None:
        path = site.folder / spec.frame
        if path.is_file():
            return path
    if frames is not None:
        for suffix in FRAME_SUFFIXES:
            path = frames / f"{camera}{suffix}"
            if path.is_file():
                return path
    return None


def _correspondences(points: Any, site: Site, unit: str) -> Any:
    if not isinstance(points, list) or not all(isinstance(point, dict) for point in points):
        raise CalibrationPageError("points must be a list of {u, v, x, y} pairs.")
    try:
        table = np.array([[float(point[key]) for key in ("u", "v", "x", "y")]
                          for point in points], dtype=np.float64).reshape(-1, 4)
    except (KeyError, TypeError, ValueError):
        raise CalibrationPageError("every pair needs numbers u, v (pixels) and x, y.") from None
    if not np.isfinite(table).all():
        raise CalibrationPageError("every pair needs finite numbers.")
    world = table[:, 2:4]
    if unit == "map":
        if site.map is None:
            raise CalibrationPageError(f"{site.source} has no map to convert map pixels.")
        world = site.map.to_world(world)
    names = [str(point.get("name") or f"p{index + 1}") for index, point in enumerate(points)]
    return Correspondences(table[:, 0:2], world, tuple(names))


def fit_points(
    site: Site,
    camera: str,
    points: Any,
    image_size: Any,
    model: str = "auto",
    focal_px: float | None = None,
    unit: str = "metres",
    left_handed: bool = False,
) -> dict[str, Any]:
    """Fit the clicked pairs; the fit's summary (:meth:`CalibrationFit.to_dict`) without the
    camera matrices, plus each inlier's reprojected pixel.

    Raises:
        CalibrationPageError: too few or degenerate points, bad values (one sentence).
    """

    site.index_of(camera)
    size = _size(image_size)
    if model not in ("auto", "homography", "pose", "focal", "k1"):
        raise CalibrationPageError(f"unknown model {model!r}.")
    try:
        pairs = _correspondences(points, site, unit)
        fit = calibrate_camera(pairs, size, camera, focal_px=focal_px, model=model,
                               left_handed=left_handed)
    except CalibrationPageError:
        raise
    except CblrsError as error:
        raise CalibrationPageError(str(error)) from None
    summary = fit.to_dict()
    summary.pop("camera")
    projected, valid = fit.camera.world_to_pixel(pairs.world_xy)
    for point, pixel, ok in zip(summary["per_point"], projected.tolist(), valid.tolist(),
                                strict=True):
        point["projected"] = pixel if ok and all(math.isfinite(v) for v in pixel) else None
    return summary


def save_points(
    site_path: Path,
    camera: str,
    points: Any,
    image_size: Any,
    references: Path,
    model: str = "auto",
    focal_px: float | None = None,
    unit: str = "metres",
    left_handed: bool = False,
) -> dict[str, Any]:
    """Write the pairs into the site file as the camera's geometry and render its reference.

    Args:
        site_path: the site file (rewritten; the previous one is kept as ``<file>.bak``).
        camera: the camera.
        points: ``[{u, v, x, y, name?}]`` (x, y in ``unit``).
        image_size: ``[width, height]`` of the camera's frames.
        references: folder of the rendered reference PNGs (``<camera>.png``).
        left_handed: the site's world axes are left-handed (mirrored points are expected).

    Returns:
        ``{"site", "backup", "reference", "fit"}``.

    Raises:
        CalibrationPageError: the fit or the site file refuses the points (nothing written).
    """
    site = load_site(site_path)
    fit = fit_points(site, camera, points, image_size, model, focal_px, unit, left_handed)
    document = read_document(site_path)
    cameras = document.get("cameras") or []
    index = site.index_of(camera)
    entry = {key: value for key, value in cameras[index].items()
             if key in ("name", "frame")}
    entry["image_size"] = _size(image_size)
    entry["points"] = [
        {"name": str(point.get("name") or f"p{number + 1}"), "u": float(point["u"]),
         "v": float(point["v"]), "x": float(point["x"]), "y": float(point["y"])}
        for number, point in enumerate(points)
    ]
    if unit == "map":
        entry["points_unit"] = "map"
    if model != "auto":
        entry["model"] = model
    if focal_px is not None:
        entry["focal_px"] = float(focal_px)
    if left_handed:
        entry["left_handed"] = True
    cameras[index] = entry
    document["cameras"] = cameras

    try:
        updated = site_from_document(document, site_path)
        reference = updated.render_reference(camera)
    except CblrsError as error:
        raise CalibrationPageError(f"not saved: {error}") from None
    backup = backup_document(site_path)  # no more open than the site file
    save_document(document, site_path)
    load_site(site_path).camera(camera)  # what was written loads, or this raises
    references.mkdir(parents=True, exist_ok=True)
    reference_path = reference.save(references / f"{camera}.png")
    return {"site": str(site_path), "backup": str(backup), "reference": str(reference_path),
            "fit": fit}


def reference_preview(site: Site, camera: str, references: Path, frames: Path | None) -> bytes:
    """PNG of the camera's saved reference over its frame (if any) with a 1 m grid."""
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    path = references / f"{camera}.png"
    if not path.is_file():
        raise CalibrationPageError(f"no reference rendered for {camera} yet; save first.")
    reference = ReferenceImage.load(path)
    frame = None
    source = frame_path(site, camera, frames)
    if source is not None:
        image = cv2.imread(str(source), cv2.IMREAD_COLOR)
        if image is not None and (image.shape[1], image.shape[0]) == reference.image_size:
            frame = np.ascontiguousarray(image[..., ::-1], dtype=np.uint8)
    picture = reference_overlay(reference, frame, grid_m=1.0)
    ok, encoded = cv2.imencode(".png", picture[..., ::-1])
    if not ok:
        raise CalibrationPageError("could not encode the preview.")
    return encoded.tobytes()


def _size(image_size: Any) -> tuple[int, int]:
    try:
        width, height = (int(value) for value in image_size)
    except (TypeError, ValueError):
        raise CalibrationPageError("image_size must be [width, height] pixels.") from None
    if width <= 0 or height <= 0:
        raise CalibrationPageError("image_size must be positive.")
    return width, height
