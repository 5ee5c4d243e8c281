"""Resolve a site camera's geometry (file, inline pose, homography or clicked points)."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cblrs.calibrate import CalibrationFit, Correspondences, calibrate_camera, pose_from_homography
from cblrs.calibration import read_cameras
from cblrs.camera import Camera
from cblrs.errors import CblrsError
from cblrs.site.schema import CameraModel, SiteError

if TYPE_CHECKING:
    from cblrs.site.core import Site, SiteCamera


def _where(site: Site, index: int, spec: CameraModel) -> str:
    return f"{site.source}: cameras[{index}] ({spec.name})"


def resolve_camera(site: Site, index: int) -> SiteCamera:
    """The :class:`SiteCamera` of ``site.model.cameras[index]``.

    Raises:
        SiteError: the geometry cannot be had (missing file, unreadable calibration, clicked
            points that cannot calibrate); one sentence naming the file and the camera.
    """
    # here, not at the top: cblrs.site.core and this module use each other
    from cblrs.site.core import SiteCamera

    spec = site.model.cameras[index]
    where = _where(site, index, spec)
    kind = spec.geometry
    fit: CalibrationFit | None = None
    try:
        if kind == "calibration":
            camera = _from_file(site, spec, where)
        elif kind == "intrinsics":
            assert spec.intrinsics is not None and spec.tvec is not None
            assert spec.image_size is not None
            rotation = spec.rotation if spec.rotation is not None else spec.rvec
            camera = Camera.from_extrinsics(
                spec.name,
                np.array(spec.intrinsics),
                np.array(rotation),
                np.array(spec.tvec),
                (spec.image_size[0], spec.image_size[1]),
                distortion=np.array(spec.distortion or []),
            )
            from cblrs.calibration import orient_cameras

            # A left-handed calibration (MultiviewX's) is converted, with a warning.
            camera = orient_cameras([camera], where)[0]
        elif kind == "homography":
            assert spec.image_size is not None
            camera = Camera.from_homography(
                spec.name, np.array(spec.homography), (spec.image_size[0], spec.image_size[1])
            )
        else:
            fit = _fit_points(site, index, spec, where)
            camera = fit.camera
    except SiteError:
        raise
    except CblrsError as error:
        raise SiteError(f"{where}.{kind}: {_sentence(error)}") from None
    position, source, note = _position(camera, spec, fit)
    return SiteCamera(spec.name, camera, position, source, note, spec, fit)


def _sentence(error: Exception) -> str:
    text = str(error).strip()
    return text if text.endswith(".") else text + "."


def _from_file(site: Site, spec: CameraModel, where: str) -> Camera:
    assert spec.calibration is not None
    reference = spec.calibration
    path = site.folder / reference.file
    if not path.exists():
        raise SiteError(f"{where}.calibration: {reference.file} does not exist (looked in {path}).")
    cameras = read_cameras(path, distorted=reference.distorted)
    wanted = reference.camera or spec.name
    chosen = [camera for camera in cameras if camera.name == wanted]
    if not chosen and reference.camera is None and len(cameras) == 1:
        chosen = cameras
    if not chosen:
        names = ", ".join(camera.name for camera in cameras)
        raise SiteError(
            f"{where}.calibration: {reference.file} has no camera {wanted!r} (it has {names}); "
            "name it with calibration: {file: ..., camera: NAME}."
        )
    camera = chosen[0]
    if camera.name != spec.name:
        camera = replace(camera, name=spec.name)
    if spec.image_size is not None and tuple(spec.image_size) != camera.image_size:
        camera = replace(camera, image_size=(spec.image_size[0], spec.image_size[1]))
    return camera


def read_points(
    site: Site, spec: CameraModel, where: str, in_metres: bool = True
) -> Correspondences:
    """The camera's clicked points; map pixels become metres unless ``in_metres`` is False."""
    transform = None
    if spec.points_unit == "map" and in_metres:
        if site.map is None:
            raise SiteError(
                f"{where}.points_unit: points in map pixels need a map with a scale "
                "(map: {metres_per_pixel: ...})."
            )
        transform = site.map.to_world
    if spec.points_file is not None:
        path = site.folder / spec.points_file
        if not path.is_file():
            raise SiteError(
                f"{where}.points: {spec.points_file} does not exist (looked in {path})."
            )
        return Correspondences.from_csv(path, transform)
    assert spec.points is not None
    rows = [point.model_dump() for point in spec.points]
    return Correspondences.from_rows(rows, f"{where}.points", transform)


def _fit_points(site: Site, index: int, spec: CameraModel, where: str) -> CalibrationFit:
    points = read_points(site, spec, where)
    assert spec.image_size is not None
    try:
        return calibrate_camera(
            points,
            (spec.image_size[0], spec.image_size[1]),
            spec.name,
            focal_px=spec.focal_px,
            model=spec.model,
            left_handed=spec.left_handed,
            **{
                key: value
                for key, value in (
                    ("click_px", spec.click_px),
                    ("ground_m", spec.ground_m),
                    ("max_height_m", spec.max_height_m),
                )
                if value is not None
            },
        )
    except CblrsError as error:
        text = _sentence(error)
        if spec.points_file is None:
            raise SiteError(text) from None
        raise SiteError(f"{where}.points: {text}") from None


def _position(
    camera: Camera, spec: CameraModel, fit: CalibrationFit | None
) -> tuple[tuple[float, float, float] | None, str, str]:
    """``(position, how it was found, why there is none)``."""
    if fit is not None:
        if fit.position is not None and fit.position[2] > 0:
            return fit.position, f"points: {fit.position_source}", ""
        return None, "", "clicked points gave no pose (see `cblrs site check`)"
    if camera.has_pose:
        centre = camera.centre
        if not centre[2] > 0:
            return None, "", "the calibrated camera is below the ground (left-handed world axes?)"
        source = "calibration file" if spec.geometry == "calibration" else "intrinsics and pose"
        return (float(centre[0]), float(centre[1]), float(centre[2])), source, ""
    recovered, reason = pose_from_homography(
        camera.homography, camera.image_size, spec.focal_px, camera.name
    )
    if recovered is None:
        return None, "", f"homography only: {reason}"
    centre = recovered.camera.centre
    how = "estimated" if recovered.focal_estimated else "given"
    return (
        (float(centre[0]), float(centre[1]), float(centre[2])),
        f"homography + {how} focal length {recovered.focal_px:.0f} px",
        "",
    )


def camera_entry(camera: Camera) -> dict[str, Any]:
    """A camera's inline site entry: K, distortion, rotation matrix, t (exact) or a homography."""
    entry: dict[str, Any] = {"name": camera.name, "image_size": list(camera.image_size)}
    if camera.has_pose:
        assert camera.intrinsics is not None and camera.rotation is not None
        assert camera.translation is not None
        entry["intrinsics"] = camera.intrinsics.tolist()
        if camera.distortion.size:
            entry["distortion"] = camera.distortion.tolist()
        # The rotation matrix, not a Rodrigues vector: converting back and forth would change
        # the last digits, and an exported site must give the same camera bit for bit.
        entry["rotation"] = camera.rotation.tolist()
        entry["tvec"] = camera.translation.tolist()
    else:
        entry["homography"] = camera.homography.tolist()
    return entry


def inline_camera(site: Site, index: int, spec: CameraModel) -> dict[str, Any]:
    """The camera's entry with its calibration file or points file inlined, keys in the
    schema's order (so that exporting an export gives the same text)."""
    data = _inline_camera(site, index, spec)
    return {key: data[key] for key in CameraModel.model_fields if key in data}


def _inline_camera(site: Site, index: int, spec: CameraModel) -> dict[str, Any]:
    data = spec.model_dump(mode="json", exclude_none=True, exclude_unset=True)
    where = _where(site, index, spec)
    if spec.geometry == "calibration":
        camera = site.camera(spec.name).camera
        entry = camera_entry(camera)
        for key in ("frame",):
            if key in data:
                entry[key] = data[key]
        return entry
    if spec.points_file is not None:
        points = read_points(site, spec, where, in_metres=False)
        data.pop("points_file", None)
        data["points"] = _point_rows(points)
    elif spec.points is not None:
        data["points"] = [
            [p.u, p.v, p.x, p.y] + ([p.name] if p.name is not None else []) for p in spec.points
        ]
    return data


def _point_rows(points: Correspondences) -> list[list[Any]]:
    rows: list[list[Any]] = []
    for index, (name, (u, v), (x, y)) in enumerate(
        zip(points.names, points.image_xy, points.world_xy, strict=True)
    ):
        row: list[Any] = [float(u), float(v), float(x), float(y)]
        if name != f"row {index + 1}":
            row.append(name)
        rows.append(row)
    return rows


def relative_path(target: Path, folder: Path) -> str:
    """``target`` relative to ``folder`` when possible (POSIX separators), else absolute."""
    try:
        return Path(os.path.relpath(target.resolve(), folder.resolve())).as_posix()
    except ValueError:
        return target.resolve().as_posix()
