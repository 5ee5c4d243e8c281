"""What the dashboard draws of a site: planes, places, cameras with their fields of view, map.

:func:`site_scene` reduces a :class:`cblrs.site.Site` to plain JSON for the page (metres
throughout; the page maps metres to its canvas). A camera's field of view is its image's
footprint on the ground: points along the image border are cast onto the plane; a border
point above the horizon is replaced by the farthest point of its column that still sees the
ground within ``max_range_m``, so a camera looking at the horizon gets a bounded footprint.
"""

from __future__ import annotations

import base64
import logging
import math
from typing import Any

import numpy as np

from cblrs.analytics.config import AnalyticsConfig
from cblrs.errors import CblrsError
from cblrs.places import line_rule_text
from cblrs.site import Site

logger = logging.getLogger(__name__)

BORDER_SAMPLES = 24
"""Points per image side of a field-of-view polygon."""


def site_scene(site: Site, plane_id: int | None = None, every_plane: bool = False
               ) -> dict[str, Any]:
    """The site as the dashboard draws it.

    Args:
        site: the site.
        plane_id: the plane shown (default: the first one); places of other planes are left
            out.
        every_plane: the overview of the site: the places of every plane (each with its
            ``plane``; ``plane`` of the scene is then None), every camera with its plane.

    Returns:
        ``{"name", "plane", "planes": [{id, name, x, y, width, length}], "zones": [{name,
        polygon}], "lines": [{name, start, end, normal, rule}], "cameras": [{name, position, fov,
        note}], "bounds": [x_min, y_min, x_max, y_max], "map": {extent, y_up} | None}``.
    """
    planes = list(site.planes or [])
    plane = plane_id if plane_id is not None else (planes[0].plane_id if planes else None)
    if every_plane:
        plane = None

    def shown(place_plane: int | None) -> bool:
        return every_plane or place_plane in (None, plane)

    zones = [
        {"name": zone.name, "polygon": zone.polygon.tolist(), "plane": zone.plane_id}
        for zone in site.places.zones
        if shown(zone.plane_id)
    ]
    # What the matcher counts as a crossing (its default settings and the lines' own), said
    # beside the counts.
    rules = dict(zip((line.name for line in site.places.lines),
                     (line_rule_text(rule, band)
                      for rule, band in AnalyticsConfig().line_rules(site.places)), strict=True))
    lines = [
        {"name": line.name, "start": line.start.tolist(), "end": line.end.tolist(),
         "normal": np.asarray(line.direction).tolist(), "rule": rules[line.name],
         "plane": line.plane_id}
        for line in site.places.lines
        if shown(line.plane_id)
    ]
    plane_boxes = [
        {"id": spec.plane_id, "name": spec.name or f"plane {spec.plane_id}",
         "x": spec.origin[0], "y": spec.origin[1], "width": spec.width, "length": spec.length}
        for spec in planes
    ]
    extent = _extent(plane_boxes, zones, lines)
    cameras = []
    for name in site.camera_names:
        view = camera_view(site, name, extent)
        view["plane"] = site.camera_plane(name)
        cameras.append(view)
    points = [[camera["position"][0], camera["position"][1]] for camera in cameras
              if camera["position"] is not None]
    bounds = _bounds(extent, points)
    site_map = None
    image = map_image(site)
    if image is not None and site.map is not None:
        # lazy: OpenCV takes ~80 ms to import; only this path needs it
        import cv2

        picture = cv2.imdecode(np.frombuffer(image[0], np.uint8), cv2.IMREAD_UNCHANGED)
        if picture is not None:
            height, width = picture.shape[:2]
            corners = site.map.to_world(np.array([[0.0, 0.0], [width, height]]))
            site_map = {
                "x_min": float(min(corners[:, 0])), "x_max": float(max(corners[:, 0])),
                "y_min": float(min(corners[:, 1])), "y_max": float(max(corners[:, 1])),
                "y_up": site.map.y_up, "type": image[1],
            }
    return {
        "name": site.name or site.source,
        "plane": plane,
        "planes": plane_boxes,
        "zones": zones,
        "lines": lines,
        "cameras": cameras,
        "bounds": bounds,
        "map": site_map,
        # The page shows times in the site's zone (Intl.DateTimeFormat), UTC without one.
        "timezone": site.model.timezone,
        "opening_hours": (None if site.calendar is None or site.calendar.opening_hours is None
                          else site.calendar.opening_hours.to_dict()),
    }


def camera_view(site: Site, name: str, extent: list[float] | None) -> dict[str, Any]:
    """One camera's position (metres, None if unknown) and ground footprint polygon."""
    try:
        resolved = site.camera(name)
    except CblrsError as error:
        return {"name": name, "position": None, "fov": [], "note": str(error)}
    position = None if resolved.position is None else [float(v) for v in resolved.position]
    reach = 50.0
    if extent is not None:
        reach = 1.5 * math.hypot(extent[2] - extent[0], extent[3] - extent[1])
    try:
        fov = field_of_view(resolved.camera, position, reach)
    except (CblrsError, ValueError, np.linalg.LinAlgError) as error:  # drawn without it
        logger.warning("no field of view for camera %s: %s", name, error)
        fov = []
    if extent is not None and fov:
        # What it sees of the site, not the far ground beyond it.
        fov = clip_to_box(fov, extent)
    return {"name": name, "position": position, "fov": fov, "note": resolved.position_note}


def field_of_view(
    camera: Any, position: list[float] | None, max_range_m: float, height_m: float = 0.0
) -> list[list[float]]:
    """The camera image's footprint on the plane ``z = height_m`` (metres), as a polygon.

    Args:
        camera: a :class:`cblrs.camera.Camera`.
        position: the camera's ground position (x, y, ...), to bound the footprint; None:
            bounded around the image centre's ground point.
        max_range_m: the farthest ground point kept, metres from the camera.
    """
    width, height = camera.image_size
    samples = np.linspace(0.0, 1.0, BORDER_SAMPLES, endpoint=False)
    border = np.concatenate([
        np.c_[samples * (width - 1), np.zeros_like(samples)],
        np.c_[np.full_like(samples, width - 1), samples * (height - 1)],
        np.c_[(1 - samples) * (width - 1), np.full_like(samples, height - 1)],
        np.c_[np.zeros_like(samples), (1 - samples) * (height - 1)],
    ])
    world, valid = camera.pixel_to_world(border, height_m)
    if position is not None:
        origin = np.array(position[:2], dtype=np.float64)
    else:
        centre, centre_valid = camera.pixel_to_world(
            np.array([[(width - 1) / 2.0, (height - 1) / 2.0]]), height_m)
        if not centre_valid[0]:
            return []
        origin = centre[0]
    near = valid & (np.hypot(*(world - origin).T) <= max_range_m)
    polygon = []
    for index, point in enumerate(border):
        if near[index]:
            polygon.append(world[index].tolist())
            continue
        # Walk down the column (towards the image bottom, nearer ground) to the first pixel
        # that sees the ground within reach.
        rows = np.linspace(point[1], height - 1, 40)
        column = np.c_[np.full_like(rows, point[0]), rows]
        ground, ok = camera.pixel_to_world(column, height_m)
        ok &= np.hypot(*(ground - origin).T) <= max_range_m
        if ok.any():
            polygon.append(ground[int(np.argmax(ok))].tolist())
    return [[round(x, 3), round(y, 3)] for x, y in polygon]


def clip_to_box(polygon: list[list[float]], box: list[float]) -> list[list[float]]:
    """A polygon clipped to ``(x_min, y_min, x_max, y_max)`` (Sutherland-Hodgman)."""
    x_min, y_min, x_max, y_max = box
    edges = (
        (lambda p: p[0] >= x_min, lambda a, b: _cut(a, b, 0, x_min)),
        (lambda p: p[0] <= x_max, lambda a, b: _cut(a, b, 0, x_max)),
        (lambda p: p[1] >= y_min, lambda a, b: _cut(a, b, 1, y_min)),
        (lambda p: p[1] <= y_max, lambda a, b: _cut(a, b, 1, y_max)),
    )
    points = [list(point) for point in polygon]
    for inside, cut in edges:
        if not points:
            break
        clipped = []
        for index, current in enumerate(points):
            previous = points[index - 1]
            if inside(current):
                if not inside(previous):
                    clipped.append(cut(previous, current))
                clipped.append(current)
            elif inside(previous):
                clipped.append(cut(previous, current))
        points = clipped
    return [[round(x, 3), round(y, 3)] for x, y in points]


def _cut(a: list[float], b: list[float], axis: int, value: float) -> list[float]:
    fraction = (value - a[axis]) / (b[axis] - a[axis])
    return [a[0] + fraction * (b[0] - a[0]), a[1] + fraction * (b[1] - a[1])]


def map_image(site: Site) -> tuple[bytes, str] | None:
    """The site map's image bytes and MIME type (from ``map.image`` or ``map.image_data``)."""
    model = site.model.map
    if model is None:
        return None
    data: bytes | None = None
    if model.image_data is not None:
        data = base64.b64decode(model.image_data)
    elif site.map is not None and site.map.image is not None:
        try:
            data = site.map.image.read_bytes()
        except OSError as error:
            logger.warning("cannot read the site map %s: %s", site.map.image, error)
            return None
    if data is None:
        return None
    kind = "image/png" if data[:8] == b"\x89PNG\r\n\x1a\n" else "image/jpeg"
    return data, kind


def _extent(planes: list[dict], zones: list[dict], lines: list[dict]) -> list[float] | None:
    points = []
    for plane in planes:
        points += [[plane["x"], plane["y"]],
                   [plane["x"] + plane["width"], plane["y"] + plane["length"]]]
    for zone in zones:
        points += zone["polygon"]
    for line in lines:
        points += [line["start"], line["end"]]
    if not points:
        return None
    array = np.asarray(points, dtype=np.float64)
    return [float(array[:, 0].min()), float(array[:, 1].min()),
            float(array[:, 0].max()), float(array[:, 1].max())]


def _bounds(extent: list[float] | None, cameras: list[list[float]]) -> list[float]:
    points = list(cameras)
    if extent is not None:
        points += [extent[:2], extent[2:]]
    if not points:
        return [-10.0, -10.0, 10.0, 10.0]
    array = np.asarray(points, dtype=np.float64)
    low, high = array.min(axis=0), array.max(axis=0)
    margin = max(1.0, 0.04 * float(np.max(high - low)))
    return [float(low[0] - margin), float(low[1] - margin),
            float(high[0] + margin), float(high[1] + margin)]
