"""A loaded site: planes, cameras (geometry resolved on demand), map and places.

:func:`load_site` validates the whole file at once (schema, duplicate names, places) but
resolves a camera's geometry only when it is asked for, so a command that needs one camera
(``cblrs camera --site``) or none (analytics on ``places``) never reads the others'
calibration files.
"""

from __future__ import annotations

import base64
import logging
import os
import stat
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.alerts.rules import AlertsError, AlertsModel, load_alerts
from cblrs.camera import Camera
from cblrs.errors import CblrsError
from cblrs.linking.links import LinkError, PlaneLink, build_links
from cblrs.localtime import LocalCalendar
from cblrs.places import PlaceError, Places
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference
from cblrs.site.schema import (
    CameraModel,
    SiteError,
    SiteModel,
    dump_document,
    parse_document,
    read_document,
    validate_document,
)

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SiteMap:
    """How site-map pixels relate to world metres.

    World ``x = (u - u0) * s`` and ``y = (v0 - v) * s`` (``y_up``, the usual plan: image rows
    grow downwards, world y upwards) or ``y = (v - v0) * s``; ``(u0, v0)`` is the map pixel of
    the world origin and ``s`` metres per pixel.
    """

    metres_per_pixel: float
    origin_px: tuple[float, float] = (0.0, 0.0)
    y_up: bool = True
    image: Path | None = None

    def to_world(self, map_px: FloatArray) -> FloatArray:
        """(N, 2) map pixels -> (N, 2) world metres."""
        points = np.asarray(map_px, dtype=np.float64).reshape(-1, 2)
        x = (points[:, 0] - self.origin_px[0]) * self.metres_per_pixel
        dy = (points[:, 1] - self.origin_px[1]) * self.metres_per_pixel
        return np.column_stack([x, -dy if self.y_up else dy])

    def to_map(self, world_xy: FloatArray) -> FloatArray:
        """(N, 2) world metres -> (N, 2) map pixels."""
        points = np.asarray(world_xy, dtype=np.float64).reshape(-1, 2)
        u = points[:, 0] / self.metres_per_pixel + self.origin_px[0]
        dv = points[:, 1] / self.metres_per_pixel
        return np.column_stack([u, self.origin_px[1] + (-dv if self.y_up else dv)])


@dataclass(frozen=True, eq=False)
class SiteCamera:
    """A site camera with its geometry resolved.

    Attributes:
        name: the camera id.
        camera: the geometry used to render its reference image.
        position: centre ``(x, y, height)`` metres when known (a pose, or a pose recovered
            from its homography), else None.
        position_source: how the position was obtained ("calibration", "points: pose", ...).
        position_note: why there is no position (empty when there is one).
        fit: the calibration from clicked points (cameras given by ``points``), else None.
        spec: the camera's entry in the site file.
    """

    name: str
    camera: Camera
    position: tuple[float, float, float] | None
    position_source: str
    position_note: str
    spec: CameraModel
    fit: Any = None


@dataclass(eq=False)
class Site:
    """A site file, validated.

    Attributes:
        path: the file it came from (None for one built in memory); relative file names in it
            are relative to its folder.
        model: the validated document.
        planes: the planes (None when the file has none).
        map: the site map (None when the file has none).
        places: zones and counting lines (empty when the file has none).
        links: where tracks pass from one plane to another (empty when the file has none).
        alerts: alert rules and webhooks (:mod:`cblrs.alerts`; none when the file has none).
    """

    path: Path | None
    model: SiteModel
    planes: PlaneSet | None
    map: SiteMap | None
    places: Places
    links: tuple[PlaneLink, ...] = ()
    alerts: AlertsModel = field(default_factory=AlertsModel)
    _resolved: dict[str, SiteCamera] = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ basics
    @property
    def source(self) -> str:
        """The file name used in messages."""
        return self.path.name if self.path is not None else "site"

    @property
    def calendar(self) -> LocalCalendar | None:
        """The site's time zone and opening hours (None: no ``timezone``, times in UTC)."""
        return self.model.calendar

    @property
    def folder(self) -> Path:
        return self.path.parent if self.path is not None else Path.cwd()

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def pseudo_key_id(self) -> str | None:
        """The key id of a pseudo site (coordinates in a keyed pseudo frame), else None."""
        return self.model.pseudo.key_id if self.model.pseudo is not None else None

    @property
    def camera_names(self) -> list[str]:
        return [camera.name for camera in self.model.cameras]

    def index_of(self, name: str) -> int:
        try:
            return self.camera_names.index(name)
        except ValueError:
            known = ", ".join(self.camera_names) or "none"
            raise SiteError(f"{self.source} has no camera {name!r} (cameras: {known}).") from None

    def camera_plane(self, name: str) -> int | None:
        """The plane a camera publishes to (its ``plane``), or None: every plane of the site."""
        return self.model.cameras[self.index_of(name)].plane

    def cameras_on(self, plane_id: int) -> list[str]:
        """Names of the cameras that publish to ``plane_id`` (those without a ``plane`` too)."""
        return [camera.name for camera in self.model.cameras
                if camera.plane is None or camera.plane == plane_id]

    def camera_planes(self, name: str) -> PlaneSet:
        """The planes a camera's reference image holds: its own plane, or every plane."""
        planes = self.require_planes("rendering a reference image")
        plane_id = self.camera_plane(name)
        return planes if plane_id is None else PlaneSet([planes.by_id(plane_id)])

    # ------------------------------------------------------------------ cameras
    def camera(self, name: str) -> SiteCamera:
        """One camera, its geometry resolved (cached)."""
        index = self.index_of(name)
        if name not in self._resolved:
            from cblrs.site.cameras import resolve_camera

            self._resolved[name] = resolve_camera(self, index)
        return self._resolved[name]

    def cameras(self) -> list[SiteCamera]:
        """Every camera, in file order, resolved."""
        return [self.camera(name) for name in self.camera_names]

    def camera_positions(self) -> dict[str, tuple[float, float, float]]:
        """``{name: (x, y, height)}`` metres of the cameras whose position is known."""
        return {
            camera.name: camera.position for camera in self.cameras() if camera.position is not None
        }

    # ------------------------------------------------------------------ what commands need
    def require_planes(self, command: str) -> PlaneSet:
        if self.planes is None:
            raise SiteError(
                f"{self.source} has no planes, which {command} needs "
                "(planes: [{id: 1, origin: [x, y], size: [width, length]}])."
            )
        return self.planes

    def require_cameras(self, command: str) -> list[SiteCamera]:
        if not self.model.cameras:
            raise SiteError(f"{self.source} has no cameras, which {command} needs.")
        return self.cameras()

    def render_reference(self, name: str, bits: int | None = None) -> Any:
        """The reference image of one camera for its planes (bits overridable): its own plane
        when it has one (``plane``), else every plane of the site."""
        planes = self.camera_planes(name)
        if bits is not None and bits != planes.bits:
            planes = PlaneSet([replace(plane, bits=bits) for plane in planes])
        return render_reference(self.camera(name).camera, planes)

    def scene(self, scene: Any) -> Any:
        """``scene`` (a :class:`cblrs.datasets.Scene`) with this site's cameras and first plane.

        The site must hold every camera of the scene (matched by name); the detections and
        ground truth are the scene's.
        """
        planes = self.require_planes("tracking a dataset with a site")
        missing = [name for name in scene.camera_names if name not in self.camera_names]
        if missing:
            raise SiteError(
                f"{self.source} has no camera {missing[0]!r} of the dataset "
                f"(dataset cameras: {', '.join(scene.camera_names)})."
            )
        cameras = [self.camera(name).camera for name in scene.camera_names]
        for camera, original in zip(cameras, scene.cameras, strict=True):
            if camera.image_size != original.image_size:
                raise SiteError(
                    f"{self.source}: camera {camera.name!r} is {camera.image_size[0]}x"
                    f"{camera.image_size[1]} but the dataset's frames are "
                    f"{original.image_size[0]}x{original.image_size[1]}."
                )
        return replace(scene, cameras=cameras, plane=planes[0])

    # ------------------------------------------------------------------ export
    def export(self) -> dict[str, Any]:
        """The site as one self-contained document: calibration files and CSV points inlined,
        the map image embedded (base64). Loading it gives the same cameras, bit for bit."""
        # here, not at the top: cblrs.site.cameras and this module use each other
        from cblrs.site.cameras import inline_camera

        data = self.model.model_dump(mode="json", exclude_none=True, exclude_unset=True)
        data["version"] = self.model.version
        cameras = []
        for index, spec in enumerate(self.model.cameras):
            cameras.append(inline_camera(self, index, spec))
        if self.model.cameras:
            data["cameras"] = cameras
        if self.model.map is not None and self.model.map.image is not None:
            image = self.folder / self.model.map.image
            try:
                payload = image.read_bytes()
            except OSError as error:
                raise SiteError(
                    f"{self.source}: map.image: cannot read {image}: {error.strerror}."
                ) from None
            site_map = data["map"]
            site_map["image_data"] = base64.b64encode(payload).decode("ascii")
            # The schema's key order, so that exporting an export gives the same text.
            data["map"] = {
                key: site_map[key]
                for key in type(self.model.map).model_fields
                if key in site_map and key != "image"
            }
        return _ordered(data)


_TOP_ORDER = ("version", "name", "pseudo", "timezone", "opening_hours", "map", "planes",
              "cameras", "places", "links", "alerts")


def _ordered(data: dict[str, Any]) -> dict[str, Any]:
    return {key: data[key] for key in _TOP_ORDER if key in data}


# ---------------------------------------------------------------------------- loading


def load_site(path: str | Path) -> Site:
    """Read and validate a site file (YAML or JSON).

    Raises:
        SiteError: one sentence naming the file and the item at fault.
    """
    path = Path(path)
    data = read_document(path)
    return site_from_document(data, path)


def site_from_document(data: dict[str, Any], path: Path | None) -> Site:
    """A :class:`Site` from a raw mapping (``path``: where relative names are relative to)."""
    source = path.name if path is not None else "site"
    model = validate_document(data, source)
    _check_names(model, source)
    planes = None
    if model.planes:
        try:
            planes = PlaneSet(
                PlaneSpec(
                    plane.id,
                    (plane.origin[0], plane.origin[1]),
                    plane.size[0],
                    plane.size[1],
                    bits=plane.bits,
                    height=plane.height,
                    name=plane.name,
                )
                for plane in model.planes
            )
        except CblrsError as error:
            raise SiteError(f"{source}: planes: {error}") from None
    site_map = None
    if model.map is not None:
        image = None
        if model.map.image is not None:
            image = (path.parent if path is not None else Path.cwd()) / model.map.image
        site_map = SiteMap(
            model.map.resolved_metres_per_pixel,
            (model.map.origin_px[0], model.map.origin_px[1]),
            model.map.y_up,
            image,
        )
    places = Places()
    if model.places is not None:
        try:
            places = Places.from_dict(model.places)
        except PlaceError as error:
            text = str(error)
            prefix = "" if text.startswith("places") else "places: "
            raise SiteError(f"{source}: {prefix}{text}") from None
    links: tuple[PlaneLink, ...] = ()
    if model.links:
        if planes is None:
            raise SiteError(f"{source}: links: the site has no planes to link.")
        try:
            links = build_links([link.model_dump(exclude_unset=True) for link in model.links],
                                planes)
        except LinkError as error:
            raise SiteError(f"{source}: {error}") from None
    try:
        alerts = load_alerts(model.alerts, source, [zone.name for zone in places.zones],
                             [line.name for line in places.lines],
                             [camera.name for camera in model.cameras] or None)
    except AlertsError as error:
        raise SiteError(str(error)) from None
    return Site(path=path, model=model, planes=planes, map=site_map, places=places, links=links,
                alerts=alerts)


def parse_site(text: str, source: str = "site.yaml", folder: Path | None = None) -> Site:
    """A site from text (YAML or JSON); relative file names are relative to ``folder``."""
    data = parse_document(text, source)
    path = (folder or Path.cwd()) / source
    return site_from_document(data, path)


def _check_names(model: SiteModel, source: str) -> None:
    seen: dict[str, int] = {}
    for index, camera in enumerate(model.cameras):
        if camera.name in seen:
            raise SiteError(
                f"{source}: cameras[{index}].name: duplicate camera name {camera.name!r} "
                f"(cameras[{seen[camera.name]}] has it too)."
            )
        seen[camera.name] = index
    plane_ids = {plane.id for plane in model.planes}
    for index, camera in enumerate(model.cameras):
        if camera.plane is not None and camera.plane not in plane_ids:
            raise SiteError(
                f"{source}: cameras[{index}].plane ({camera.name}): no plane {camera.plane} "
                f"(planes: {sorted(plane_ids) or 'none'})."
            )
    ids: dict[int, int] = {}
    for index, plane in enumerate(model.planes):
        if plane.id in ids:
            raise SiteError(
                f"{source}: planes[{index}].id: duplicate plane id {plane.id} "
                f"(planes[{ids[plane.id]}] has it too)."
            )
        ids[plane.id] = index
    bits = {plane.bits for plane in model.planes}
    if len(bits) > 1:
        raise SiteError(
            f"{source}: planes: all planes need the same bits (one reference image holds them "
            f"all), got {sorted(bits)}."
        )


def save_document(data: dict[str, Any], path: str | Path) -> Path:
    """Write a site document (YAML, or JSON for ``.json``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_document(data, path))
    return path


def backup_document(path: str | Path) -> Path:
    """Copy the site file ``path`` to ``<file>.bak`` (replaced), no more open than the file.

    The copy is created 0600 and only then given the file's own mode: a site file its owner
    keeps 0600 (its webhooks' addresses, its calibrations) does not get a backup that every
    user of the machine reads (``shutil.copyfile`` made it 0644 under the usual umask). A
    symbolic link at the backup's name is refused, not followed.
    """
    path = Path(path)
    backup = path.with_name(path.name + ".bak")
    mode = stat.S_IMODE(path.stat().st_mode)
    data = path.read_bytes()
    descriptor = os.open(backup, os.O_WRONLY | os.O_CREAT | os.O_TRUNC
                         | getattr(os, "O_NOFOLLOW", 0), 0o600)
    with os.fdopen(descriptor, "wb") as out:
        if hasattr(os, "fchmod"):
            os.fchmod(descriptor, 0o600)  # an older backup may be more open
        out.write(data)
        if hasattr(os, "fchmod"):
            os.fchmod(descriptor, mode)
    return backup
