"""Carrying a site into pseudo coordinates with its key: references, cameras, places, tracks.

Who does what:

* the **site owner** holds the real site file and the key: renders the cameras' pseudo
  references (:func:`render_pseudo_reference`) and writes once a **pseudo site**
  (:func:`pseudo_site_document`) — planes, cameras and places, every coordinate in the pseudo
  frame, no map, no file names, no clicked points, no plane or site names;
* the **matcher** is given the pseudo site like any site file: it needs no key. Its tracker
  works on pseudo metres, its analytics count against the pseudo places (a rigid transform
  keeps which side of a line and which zone a point is in), and its database, tracks and
  events hold pseudo coordinates only;
* a **key holder** maps tracks and events back (:func:`tracks_to_site`): ``cblrs eval
  --key``, ``cblrs pseudo unmap``, the dashboard with ``--key``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from cblrs.camera import Camera
from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.places import CountingLine, Places, Zone
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.privacy.key import PseudoKey
from cblrs.reference import ReferenceImage, render_reference

POSITION_TOLERANCE_M = 0.01
"""How far a camera's position in the pseudo site may be from its transformed real one."""


def render_pseudo_reference(
    camera: Camera, planes: PlaneSet | PlaneSpec, key: PseudoKey
) -> ReferenceImage:
    """A camera's reference image whose colours encode pseudo coordinates.

    The pixels that see a plane are exactly those of the plain reference (the real plane
    decides, not its larger pseudo square); their colours are the key's transform of the
    point seen, encoded in :meth:`PseudoKey.pseudo_planes`. The PNG's plane specification is
    the pseudo one.

    Args:
        camera: the camera, real site coordinates.
        planes: the site's planes.
        key: the site owner's key.
    """
    if isinstance(planes, PlaneSpec):
        planes = PlaneSet([planes])
    return render_reference(camera, planes, encode_as=(key.matrix, key.pseudo_planes(planes)))


def pseudo_camera(camera: Camera, key: PseudoKey) -> Camera:
    """The same camera in the pseudo frame (its images and pixels unchanged).

    A posed camera gets ``R' = R diag(Q^T, 1)`` and ``t' = t - R' (b, 0)``; a homography-only
    one ``H' = H M^-1`` with ``M`` the key's homogeneous ground transform.
    """
    if camera.has_pose:
        assert camera.rotation is not None and camera.translation is not None
        assert camera.intrinsics is not None
        inverse = np.eye(3)
        inverse[:2, :2] = key.rotation.T
        rotation = camera.rotation @ inverse
        translation = camera.translation - rotation @ np.array([*key.translation, 0.0])
        return Camera.from_extrinsics(
            camera.name, camera.intrinsics, rotation, translation, camera.image_size,
            distortion=camera.distortion, height_axis=camera.height_axis,
        )
    homography = camera.homography @ np.linalg.inv(key.matrix)
    return Camera(name=camera.name, image_size=camera.image_size, homography=homography)


def pseudo_places(places: Places, key: PseudoKey) -> Places:
    """Zones and lines in the pseudo frame (line directions rotated, so each keeps its
    positive side)."""
    zones = tuple(
        Zone(zone.name, key.to_pseudo(zone.polygon), zone.plane_id, zone.hysteresis_m)
        for zone in places.zones
    )
    lines = []
    for line in places.lines:
        assert line.direction is not None
        start, end = key.to_pseudo(np.stack([line.start, line.end]))
        direction = key.direction_to_pseudo(line.direction[None])[0]
        lines.append(
            CountingLine(line.name, start, end, direction=direction, plane_id=line.plane_id,
                         hysteresis_m=line.hysteresis_m)
        )
    return Places(zones, tuple(lines))


def positions_to_pseudo(
    positions: dict[str, tuple[float, float, float]], key: PseudoKey
) -> dict[str, tuple[float, float, float]]:
    """Camera positions ``{name: (x, y, height)}`` in the pseudo frame (heights kept)."""
    pseudo = {}
    for name, (x, y, height) in positions.items():
        px, py = key.to_pseudo(np.array([[x, y]]))[0]
        pseudo[name] = (float(px), float(py), float(height))
    return pseudo


def tracks_to_site(tracks: Tracks, key: PseudoKey) -> Tracks:
    """Pseudo tracks mapped back to site metres (everything else unchanged)."""
    return replace(tracks, world_xy=key.to_site(tracks.world_xy))


def tracks_to_pseudo(tracks: Tracks, key: PseudoKey) -> Tracks:
    """Site tracks in the pseudo frame (ground truth, for comparisons)."""
    return replace(tracks, world_xy=key.to_pseudo(tracks.world_xy))


def pseudo_site_document(site: Any, key: PseudoKey) -> dict[str, Any]:
    """The pseudo site of a real one: what the matcher (and a keyless dashboard) is given.

    Args:
        site: a :class:`cblrs.site.Site` with planes and cameras (real coordinates).
        key: the site owner's key.

    Returns:
        A site document (``version``, ``name``, ``pseudo``, ``planes``, ``cameras``,
        ``places``) whose every coordinate is in the pseudo frame; cameras are inlined
        (intrinsics and pose, or a homography with its focal length), without calibration
        files, clicked points or frame pictures; no map; planes and site without names.

    Raises:
        CblrsError: the site has no planes or cameras, or a camera's position could not be
            carried over (it would then differ between the real and the pseudo site).
    """
    # here, not at the top: cblrs.site imports the calibration stack, which only this needs
    from cblrs.site.cameras import camera_entry
    from cblrs.site.core import site_from_document

    planes = site.require_planes("a pseudo site")
    cameras = site.require_cameras("a pseudo site")
    document: dict[str, Any] = {
        "version": 1,
        "name": f"pseudo-{key.key_id}",
        "pseudo": {"key_id": key.key_id},
        "planes": [
            {"id": plane.plane_id, "origin": list(plane.origin),
             "size": [plane.width, plane.length], "bits": plane.bits, "height": plane.height}
            for plane in key.pseudo_planes(planes)
        ],
        "cameras": [],
    }
    for site_camera in cameras:
        entry = camera_entry(pseudo_camera(_posed(site_camera), key))
        focal = _focal_px(site_camera)
        if "homography" in entry and focal is not None:
            entry["focal_px"] = focal
        document["cameras"].append(entry)
    if len(site.places):
        document["places"] = pseudo_places(site.places, key).to_dict()
    _check_positions(site, site_from_document(document, None), key)
    return document


def _posed(site_camera: Any) -> Camera:
    """The camera with a pose where its position came from one.

    A homography-only camera's position is recovered from its homography (a scale fitted to
    two columns that are never exactly orthonormal), which a rotation of the world changes by
    centimetres; the recovered pose itself moves exactly, so it is what the pseudo site gets.
    """
    camera = site_camera.camera
    if camera.has_pose or site_camera.position is None:
        return camera
    # here, not at the top: the calibration stack is needed only for such cameras
    from cblrs.calibrate import pose_from_homography

    recovered, _ = pose_from_homography(
        camera.homography, camera.image_size, _focal_px(site_camera), camera.name
    )
    if recovered is None:
        return camera
    centre = recovered.camera.centre
    if np.linalg.norm(centre - np.asarray(site_camera.position)) > POSITION_TOLERANCE_M:
        return camera  # a position from a fitted pose: carried by the homography, checked
    return recovered.camera


def _focal_px(site_camera: Any) -> float | None:
    """The focal length that gave a homography-only camera its position, if any."""
    if site_camera.fit is not None and site_camera.fit.focal_px is not None:
        return float(site_camera.fit.focal_px)
    if site_camera.spec.focal_px is not None:
        return float(site_camera.spec.focal_px)
    return None


def _check_positions(site: Any, pseudo: Any, key: PseudoKey) -> None:
    real = positions_to_pseudo(site.camera_positions(), key)
    carried = pseudo.camera_positions()
    for name, position in real.items():
        moved = carried.get(name)
        if moved is None or np.hypot(*np.subtract(moved[:2], position[:2])) > POSITION_TOLERANCE_M \
                or abs(moved[2] - position[2]) > POSITION_TOLERANCE_M:
            raise CblrsError(
                f"camera {name!r}: its position could not be carried into the pseudo frame "
                f"(expected {np.round(position, 2).tolist()}, got "
                f"{None if moved is None else np.round(moved, 2).tolist()}); give it a "
                "calibration with a pose (intrinsics and rvec/rotation and tvec)."
            )
