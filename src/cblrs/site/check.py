"""``cblrs site check``: is a site file valid, and what is it ready for?"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cblrs.site.core import Site, site_from_document
from cblrs.site.schema import SiteError, problems, read_document

COMMANDS = ("render", "camera", "matcher", "track", "analytics")
"""What ``check`` reports readiness for (``track`` stands for track, eval and demo --site)."""

# Pixels sampled per camera to measure how much of the image sees a plane.
_SAMPLES = (48, 27)


def check_site(path: str | Path) -> dict[str, Any]:
    """Validate a site file completely and say what each command would miss.

    Unlike :func:`cblrs.site.load_site` (which stops at the first problem) this reports
    every schema problem, resolves every camera separately and measures, per camera, the
    fraction of its image that sees one of the planes.

    Returns:
        JSON-ready ``{"file", "valid", "problems", "warnings", "planes", "cameras", "map",
        "places", "ready": {command: bool}, "missing": {command: [sentences]}}``.
    """
    path = Path(path)
    report: dict[str, Any] = {
        "file": str(path),
        "valid": False,
        "problems": [],
        "warnings": [],
        "planes": [],
        "cameras": [],
        "map": None,
        "places": {"zones": 0, "lines": 0},
        "ready": dict.fromkeys(COMMANDS, False),
        "missing": {},
    }
    data = read_document(path)
    report["problems"] = problems(data, path.name)
    if report["problems"]:
        return report
    try:
        site = site_from_document(data, path)
    except SiteError as error:
        report["problems"] = [str(error)]
        return report
    report["valid"] = True
    report["name"] = site.name
    report["pseudo_key_id"] = site.pseudo_key_id
    report["planes"] = site.planes.to_list() if site.planes is not None else []
    if site.map is not None:
        report["map"] = {
            "metres_per_pixel": site.map.metres_per_pixel,
            "origin_px": list(site.map.origin_px),
            "y_up": site.map.y_up,
            "image": str(site.map.image) if site.map.image is not None else None,
        }
        if site.map.image is not None and not site.map.image.is_file():
            report["warnings"].append(f"{site.source}: map.image: {site.map.image} does not exist.")
    report["places"] = {
        "zones": len(site.places.zones),
        "lines": len(site.places.lines),
        "names": site.places.names,
    }
    calendar = site.calendar
    report["timezone"] = None if calendar is None else calendar.timezone
    report["opening_hours"] = (None if calendar is None or calendar.opening_hours is None
                               else calendar.opening_hours.to_dict())
    cameras = [_camera_report(site, name) for name in site.camera_names]
    report["cameras"] = cameras
    for camera in cameras:
        report["warnings"].extend(camera.pop("warnings"))
    report["missing"] = _missing(site, cameras)
    report["ready"] = {command: not report["missing"].get(command) for command in COMMANDS}
    return report


def _camera_report(site: Site, name: str) -> dict[str, Any]:
    index = site.index_of(name)
    spec = site.model.cameras[index]
    entry: dict[str, Any] = {
        "name": name,
        "geometry": spec.geometry,
        "ok": False,
        "error": None,
        "warnings": [],
    }
    try:
        resolved = site.camera(name)
    except SiteError as error:
        entry["error"] = str(error)
        return entry
    camera = resolved.camera
    entry.update(
        ok=True,
        image_size=list(camera.image_size),
        posed=camera.has_pose,
        distorted=camera.has_distortion,
        position=list(resolved.position) if resolved.position is not None else None,
        position_source=resolved.position_source,
        position_note=resolved.position_note,
    )
    if resolved.fit is not None:
        fit = resolved.fit
        entry["calibration"] = {
            "model": fit.model.value,
            "points": len(fit.points),
            "inliers": int(fit.inliers.sum()),
            "rms_px": fit.rms_px,
            "median_error_m": float(np.nanmedian(fit.error_m[fit.inliers])),
            "focal_px": fit.focal_px,
        }
        entry["warnings"].extend(fit.warnings)
    if site.planes is not None:
        coverage = plane_coverage(camera, site.planes)
        entry["coverage"] = coverage
        if coverage == 0:
            entry["warnings"].append(
                f"{site.source}: camera {name!r} sees none of the planes (check its geometry "
                "and the planes' extent)."
            )
    return entry


def plane_coverage(camera: Any, planes: Any) -> float:
    """Fraction of a coarse pixel grid whose ray meets one of the planes."""
    width, height = camera.image_size
    u, v = np.meshgrid(
        np.linspace(0, width - 1, _SAMPLES[0]), np.linspace(0, height - 1, _SAMPLES[1])
    )
    pixels = np.column_stack([u.ravel(), v.ravel()])
    seen = np.zeros(len(pixels), dtype=bool)
    for plane in planes:
        if plane.height != 0 and not camera.has_pose:
            continue
        world, valid = camera.pixel_to_world(pixels, plane.height)
        seen |= valid & plane.contains(np.where(valid[:, None], world, np.inf))
    return float(seen.mean())


def _missing(site: Site, cameras: list[dict[str, Any]]) -> dict[str, list[str]]:
    missing: dict[str, list[str]] = {command: [] for command in COMMANDS}
    broken = [camera for camera in cameras if not camera["ok"]]
    if site.planes is None:
        for command in ("render", "camera", "matcher", "track"):
            missing[command].append("no planes (planes: [{id, origin, size}])")
    if not cameras:
        for command in ("render", "camera", "matcher", "track"):
            missing[command].append("no cameras")
    for camera in broken:
        text = f"camera {camera['name']!r} has no usable geometry"
        missing["render"].append(text)
        missing["track"].append(text)
        missing["matcher"].append(text)
    if broken and len(broken) == len(cameras):
        missing["camera"].append("no camera has a usable geometry")
    if not site.places.zones and not site.places.lines:
        missing["analytics"].append("no places (places: {zones: [...], lines: [...]})")
    if site.pseudo_key_id is not None:
        # The pseudo plane is a larger square: colours of this file's cameras would cover
        # more than the real plane. References come from the real site and the key.
        for command in ("render", "camera", "track"):
            missing[command].append(
                f"a pseudo site (key {site.pseudo_key_id}): use the real site with --key"
            )
    return {command: reasons for command, reasons in missing.items() if reasons}


def format_check(report: dict[str, Any]) -> str:
    """The report as text for a terminal."""
    lines = []
    name = report["file"]
    if not report["valid"]:
        lines.append(f"{name}: INVALID")
        lines.extend(f"  {problem}" for problem in report["problems"])
        return "\n".join(lines)
    lines.append(f"{name}: valid site {report.get('name') or ''!r}".rstrip())
    if report.get("pseudo_key_id"):
        lines.append(f"  pseudo site: coordinates in the pseudo frame of key "
                     f"{report['pseudo_key_id']} (for the matcher and a keyless dashboard)")
    planes = report["planes"]
    if planes:
        for plane in planes:
            lines.append(
                f"  plane {plane['plane_id']}{' ' + plane['name'] if plane['name'] else ''}: "
                "origin "
                f"({plane['origin'][0]:g}, {plane['origin'][1]:g}) m, {plane['width']:g} x "
                f"{plane['length']:g} m, height {plane['height']:g} m, {plane['bits']} bit"
            )
    else:
        lines.append("  planes: none")
    if report["map"]:
        site_map = report["map"]
        lines.append(
            f"  map: {site_map['metres_per_pixel']:g} m per pixel, origin at map pixel "
            f"({site_map['origin_px'][0]:g}, {site_map['origin_px'][1]:g})"
        )
    lines.append(f"  cameras: {len(report['cameras'])}")
    for camera in report["cameras"]:
        if not camera["ok"]:
            lines.append(f"    {camera['name']}: ERROR {camera['error']}")
            continue
        position = camera["position"]
        where = (
            f"at ({position[0]:.2f}, {position[1]:.2f}) m, {position[2]:.2f} m high "
            f"[{camera['position_source']}]"
            if position
            else f"no position ({camera['position_note']})"
        )
        fit = camera.get("calibration")
        fitted = (
            f", {fit['model']} from {fit['inliers']}/{fit['points']} points, "
            f"RMS {fit['rms_px']:.1f} px"
            if fit
            else ""
        )
        coverage = (
            f", sees a plane in {100 * camera['coverage']:.0f} % of the image"
            if "coverage" in camera
            else ""
        )
        lines.append(f"    {camera['name']}: {camera['geometry']}{fitted}, {where}{coverage}")
    places = report["places"]
    lines.append(f"  places: {places['zones']} zones, {places['lines']} lines")
    if report.get("timezone"):
        hours = report.get("opening_hours")
        open_text = ("always open" if hours is None else
                     "open " + ", ".join(f"{day} {text}" for day, text in hours.items()))
        lines.append(f"  local time: {report['timezone']}, {open_text}")
    for warning in report["warnings"]:
        lines.append(f"  warning: {warning}")
    ready = [command for command, ok in report["ready"].items() if ok]
    lines.append(f"ready for: {', '.join(ready) if ready else 'nothing yet'}")
    for command, reasons in report["missing"].items():
        lines.append(f"missing for {command}: {'; '.join(reasons)}")
    return "\n".join(lines)
