"""The site file's schema: pydantic models (unknown keys are errors) and reading/writing.

A site file is YAML (``.yaml``/``.yml``) or JSON (``.json``) holding::

    version: 1
    name: my-site
    planes: [{id, name, origin: [x, y], size: [width, length], bits, height}]
    cameras: [{name, image_size, <one geometry>, plane, ...}]
    map: {image, metres_per_pixel | scale: {pixels, metres}, origin_px, y_up}
    places: {zones: [...], lines: [...]}        # cblrs.places
    links: [{planes: [a, b], portals, transit_s, max_distance_m}]   # cblrs.linking
    pseudo: {key_id}                            # a pseudo site (cblrs.privacy)
    timezone: Europe/Zurich                     # IANA zone of local times (cblrs.localtime)
    opening_hours: {mon-fri: "07:00-19:00", sun: closed}   # counting and alerts (idem)
    camera_fps: 10                              # cameras' frame rate when they give no fps

Every section but ``version`` may be left out; each command checks what it needs. A camera's
geometry is exactly one of: ``calibration`` (a file: cblrs camera JSON, an AI City
``calibration.json``, or a WILDTRACK/MultiviewX folder with ``camera`` naming the camera in
it), ``intrinsics`` with ``rotation``/``rvec`` and ``tvec`` (and optional ``distortion``),
``homography`` (world metres -> pixels), or ``points`` (clicked image <-> world
correspondences, inline or a CSV file, calibrated on load by :mod:`cblrs.calibrate`).

Validation errors become one sentence naming the file and the key's path, e.g.
``site.yaml: cameras[2].intrinsics: expected a 3x3 matrix``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from cblrs.errors import CblrsError
from cblrs.localtime import LocalCalendar, LocalTimeError, OpeningHours, time_zone
from cblrs.names import check_name
from cblrs.site.sources import DetectorModel, FrameRate, SourceModel

SITE_VERSION = 1


class SiteError(CblrsError):
    """A site file is missing, malformed, or lacks what a command needs."""


# ---------------------------------------------------------------------------- field types


def _numbers(value: Any, count: int | None, what: str) -> list[float]:
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__"):
        raise ValueError(f"expected {what}")
    if count is not None and len(value) != count:
        raise ValueError(f"expected {what}")
    numbers = []
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int | float):
            raise ValueError(f"expected {what}")
        number = float(item)
        if not math.isfinite(number):
            raise ValueError(f"expected {what} (finite numbers)")
        numbers.append(number)
    return numbers


def _matrix3(value: Any) -> list[list[float]]:
    what = "a 3x3 matrix"
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__") or len(value) != 3:
        raise ValueError(f"expected {what}")
    return [_numbers(row, 3, what) for row in value]


def _vector(count: int) -> Any:
    return BeforeValidator(lambda value: _numbers(value, count, f"{count} numbers"))


Matrix3 = Annotated[list[list[float]], BeforeValidator(_matrix3)]
Vector2 = Annotated[list[float], _vector(2)]
Vector3 = Annotated[list[float], _vector(3)]
Coefficients = Annotated[
    list[float], BeforeValidator(lambda value: _numbers(value, None, "a list of numbers"))
]


def _image_size(value: Any) -> list[int]:
    numbers = _numbers(value, 2, "[width, height] in pixels")
    if not all(number > 0 and number == int(number) for number in numbers):
        raise ValueError("expected [width, height] in pixels (positive whole numbers)")
    return [int(number) for number in numbers]


ImageSize = Annotated[list[int], BeforeValidator(_image_size)]


def _optional_name(what: str) -> AfterValidator:
    """A validator of a name that may be empty ("" or None: no name)."""

    def check(name: str | None) -> str | None:
        return name if not name else check_name(name, what)

    return AfterValidator(check)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ---------------------------------------------------------------------------- sections


class PlaneModel(_Strict):
    """A colour-coded plane (:class:`cblrs.plane.PlaneSpec`), metres."""

    id: int = Field(ge=1, le=65535)
    name: Annotated[str, _optional_name("plane name")] = ""
    origin: Vector2
    size: Vector2
    bits: Literal[8, 16] = 16
    height: float = 0.0

    @model_validator(mode="after")
    def _positive_size(self) -> PlaneModel:
        if not (self.size[0] > 0 and self.size[1] > 0):
            raise ValueError(f"size must be positive [width, length] metres, got {self.size}")
        if not math.isfinite(self.height):
            raise ValueError("height must be a finite number of metres")
        return self


class ScaleModel(_Strict):
    """A drawn scale bar: ``pixels`` map pixels are ``metres`` metres."""

    pixels: float = Field(gt=0)
    metres: float = Field(gt=0)


class MapModel(_Strict):
    """The site plan: a map image and how its pixels relate to world metres."""

    image: str | None = None
    image_data: str | None = None  # base64 PNG/JPEG, written by `cblrs site export`
    metres_per_pixel: float | None = Field(default=None, gt=0)
    scale: ScaleModel | None = None
    origin_px: Vector2 = Field(default_factory=lambda: [0.0, 0.0])
    y_up: bool = True

    @model_validator(mode="after")
    def _scale(self) -> MapModel:
        if self.metres_per_pixel is None and self.scale is None:
            raise ValueError(
                "a map needs a scale: give metres_per_pixel or scale: {pixels: P, metres: M}"
            )
        if self.metres_per_pixel is not None and self.scale is not None:
            raise ValueError("give metres_per_pixel or scale, not both")
        if self.image is not None and self.image_data is not None:
            raise ValueError("give image or image_data, not both")
        return self

    @property
    def resolved_metres_per_pixel(self) -> float:
        if self.metres_per_pixel is not None:
            return self.metres_per_pixel
        assert self.scale is not None
        return self.scale.metres / self.scale.pixels


class CalibrationRefModel(_Strict):
    """A calibration kept in a file (path relative to the site file)."""

    file: str = Field(min_length=1)
    camera: str | None = None
    distorted: bool = False


class PointModel(_Strict):
    """One clicked correspondence: pixel (u, v) <-> world (x, y)."""

    name: Annotated[str | None, _optional_name("point name")] = None
    u: float
    v: float
    x: float
    y: float


def _calibration_ref(value: Any) -> Any:
    return {"file": value} if isinstance(value, str) else value


def _points(value: Any) -> Any:
    if isinstance(value, list):
        rows = []
        for row in value:
            if isinstance(row, list | tuple) and len(row) in (4, 5):
                keys = ("u", "v", "x", "y", "name")
                rows.append(dict(zip(keys, row, strict=False)))
            else:
                rows.append(row)
        return rows
    return value


def _camera_name_text(name: str) -> str:
    if (
        not name
        or any(character in name for character in "/+#")
        or name != name.strip()
        or (any(character.isspace() for character in name))
    ):
        raise ValueError(
            f"camera name {name!r} must be non-empty without '/', '+', '#' or spaces "
            "(it is part of MQTT topics)"
        )
    return check_name(name, "camera name")


MODELS = ("auto", "homography", "pose", "focal", "k1")
GEOMETRY_KEYS = ("calibration", "intrinsics", "homography", "points")


class CameraModel(_Strict):
    """One camera: a name, its image size and exactly one geometry."""

    name: Annotated[str, AfterValidator(_camera_name_text)]
    image_size: ImageSize | None = None
    calibration: Annotated[CalibrationRefModel | None, BeforeValidator(_calibration_ref)] = None
    intrinsics: Matrix3 | None = None
    distortion: Coefficients | None = None
    rotation: Matrix3 | None = None
    rvec: Vector3 | None = None
    tvec: Vector3 | None = None
    homography: Matrix3 | None = None
    points: Annotated[list[PointModel] | None, BeforeValidator(_points)] = None
    points_file: str | None = None
    points_unit: Literal["metres", "map"] = "metres"
    focal_px: float | None = Field(default=None, gt=0)
    model: Literal["auto", "homography", "pose", "focal", "k1"] = "auto"
    # How far clicks and the points' ground positions may be off (one standard deviation).
    click_px: float | None = Field(default=None, gt=0)
    ground_m: float | None = Field(default=None, gt=0)
    # What a plausible fit of clicked points is (cblrs.calibrate.plausible).
    left_handed: bool = False
    max_height_m: float | None = Field(default=None, gt=0)
    frame: str | None = None
    # The plane whose matcher the camera publishes to (its reference holds only that plane);
    # absent: every plane of the site (a site of one plane needs no more).
    plane: int | None = Field(default=None, ge=1, le=65535)
    # What `cblrs up` runs for this camera (absent: the camera runs elsewhere, or not yet).
    source: SourceModel | None = None
    # The frames per second it sends (default: the site's camera_fps, else its source's fps);
    # `cblrs up` tells its plane's matcher the fastest (cblrs matcher --camera-fps).
    fps: FrameRate | None = None

    @model_validator(mode="before")
    @classmethod
    def _points_from_file(cls, data: Any) -> Any:
        # `points: pts.csv` names a file; keep the two forms apart internally.
        if isinstance(data, dict) and isinstance(data.get("points"), str):
            data = dict(data)
            if "points_file" in data:
                raise ValueError("give points or points_file, not both")
            data["points_file"] = data.pop("points")
        return data

    @model_validator(mode="after")
    def _one_geometry(self) -> CameraModel:
        given = [key for key in GEOMETRY_KEYS if getattr(self, key) is not None]
        if self.points_file is not None:
            given.append("points")
        if not given:
            raise ValueError(
                "no geometry: give one of calibration (a file), intrinsics with rvec or rotation "
                "and tvec, homography, or points (clicked correspondences)"
            )
        if len(given) > 1:
            raise ValueError(f"give one geometry, not {' and '.join(given)}")
        kind = given[0]
        if kind == "intrinsics":
            if (self.rotation is None) == (self.rvec is None):
                raise ValueError("intrinsics need exactly one of rotation (3x3) or rvec (3)")
            if self.tvec is None:
                raise ValueError("intrinsics need tvec (world -> camera translation, metres)")
        else:
            extra = [k for k in ("distortion", "rotation", "rvec", "tvec") if getattr(self, k)]
            if extra:
                raise ValueError(f"{extra[0]} belongs with intrinsics, not with {kind}")
        if kind != "calibration" and self.image_size is None:
            raise ValueError(f"a camera given by {kind} needs image_size: [width, height]")
        if self.focal_px is not None and kind not in ("homography", "points"):
            raise ValueError("focal_px is for cameras given by homography or points")
        if kind != "points" and (
            "model" in self.model_fields_set
            or self.points_unit != "metres"
            or self.click_px is not None
            or self.ground_m is not None
            or self.left_handed
            or self.max_height_m is not None
        ):
            raise ValueError(
                "model, points_unit, click_px, ground_m, left_handed and max_height_m are for "
                "cameras given by points"
            )
        return self

    @property
    def geometry(self) -> str:
        """Which geometry the camera has: calibration, intrinsics, homography or points."""
        if self.points_file is not None:
            return "points"
        return next(key for key in GEOMETRY_KEYS if getattr(self, key) is not None)


def _polygon(value: Any) -> list[list[float]]:
    what = "a polygon: a list of at least 3 [x, y] points in metres"
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__") or len(value) < 3:
        raise ValueError(f"expected {what}")
    return [_numbers(point, 2, what) for point in value]


Polygon = Annotated[list[list[float]], BeforeValidator(_polygon)]


class LinkModel(_Strict):
    """Where tracks pass from one plane to another (:mod:`cblrs.linking`).

    Without ``portals`` the two planes overlap (same height, rectangles that intersect) and a
    track is handed over where both planes' cameras see it; with them, ``portals[0]`` (on the
    first plane) and ``portals[1]`` (on the second) are where tracks leave one plane and appear
    on the other, ``transit_s`` seconds later (stairs, a tunnel, a street without cameras).
    """

    planes: Annotated[list[int], _vector(2)]
    portals: list[Polygon] | None = None
    transit_s: Annotated[list[float], _vector(2)] = Field(default_factory=lambda: [0.0, 30.0])
    max_distance_m: float = Field(default=1.5, gt=0)

    @model_validator(mode="after")
    def _consistent(self) -> LinkModel:
        first, second = self.planes
        if min(first, second) < 1:
            raise ValueError("planes must be two plane ids (whole numbers from 1)")
        if first == second:
            raise ValueError(f"a link joins two different planes, got {first} twice")
        if self.portals is not None and len(self.portals) != 2:
            raise ValueError(
                "portals must be two polygons: where tracks leave or enter the first plane, "
                "then the second"
            )
        low, high = self.transit_s
        if not 0 <= low <= high:
            raise ValueError(f"transit_s must be [min, max] seconds with 0 <= min <= max, "
                             f"got {self.transit_s}")
        return self


class PseudoModel(_Strict):
    """Marks a pseudo site (:mod:`cblrs.privacy`): every coordinate is in the pseudo frame of
    the key named here; the key itself is never in a site file."""

    key_id: Annotated[str, Field(pattern=r"^[0-9a-f]{8}$")]


def _zone_name(name: str | None) -> str | None:
    if name is not None:
        try:
            time_zone(name)
        except LocalTimeError as error:
            raise ValueError(str(error)) from None
    return name


def _hours(hours: dict[str, Any] | None) -> dict[str, Any] | None:
    if hours is not None:
        try:
            OpeningHours.parse(hours)
        except LocalTimeError as error:
            raise ValueError(str(error).removeprefix("opening_hours: ")) from None
    return hours


class SiteModel(_Strict):
    """The whole site file."""

    version: Literal[1]
    name: Annotated[str, _optional_name("site name")] = ""
    pseudo: PseudoModel | None = None
    planes: list[PlaneModel] = Field(default_factory=list)
    cameras: list[CameraModel] = Field(default_factory=list)
    map: MapModel | None = None
    places: dict[str, Any] | None = None
    links: list[LinkModel] = Field(default_factory=list)
    alerts: dict[str, Any] | None = None  # cblrs.alerts.rules checks it
    timezone: Annotated[str | None, AfterValidator(_zone_name)] = None
    opening_hours: Annotated[dict[str, Any] | None, AfterValidator(_hours)] = None
    camera_fps: FrameRate | None = None  # a camera's fps when it gives none (cblrs up)

    @model_validator(mode="after")
    def _hours_need_zone(self) -> SiteModel:
        if self.opening_hours is not None and self.timezone is None:
            raise ValueError(
                "opening_hours need the site's timezone (add e.g. timezone: Europe/Zurich)"
            )
        return self

    @property
    def calendar(self) -> LocalCalendar | None:
        """The site's local time and opening hours (None without a ``timezone``)."""
        return LocalCalendar.of(self.timezone, self.opening_hours)


# ---------------------------------------------------------------------------- errors


def location(loc: tuple[int | str, ...]) -> str:
    """``("cameras", 2, "intrinsics")`` -> ``"cameras[2].intrinsics"``."""
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text or "(top level)"


def error_sentences(error: ValidationError, source: str, data: Any = None) -> list[str]:
    """One sentence per pydantic error: ``"<source>: <path>: <what is wrong>"``."""
    sentences = []
    for item in error.errors(include_url=False):
        loc = tuple(item["loc"])
        kind = item["type"]
        message = str(item["msg"])
        if message.startswith("Value error, "):
            message = message[len("Value error, ") :]
        if kind == "extra_forbidden":
            message = "unknown key" + _allowed_keys(loc)
        elif kind == "missing":
            message = "required key is missing"
        elif kind == "literal_error" and loc == ("version",):
            message = f"this cblrs reads site files of version {SITE_VERSION}"
        name = _camera_name(loc, data)
        path = location(loc)
        if name and len(loc) == 2:
            path += f" ({name})"
        sentences.append(f"{source}: {path}: {message.rstrip('.')}.")
    return sentences


def _camera_name(loc: tuple[int | str, ...], data: Any) -> str | None:
    if len(loc) >= 2 and loc[0] == "cameras" and isinstance(loc[1], int) and isinstance(data, dict):
        cameras = data.get("cameras")
        if (
            isinstance(cameras, list)
            and loc[1] < len(cameras)
            and isinstance(cameras[loc[1]], dict)
        ):
            name = cameras[loc[1]].get("name")
            return str(name) if name else None
    return None


_MODELS_BY_SECTION: dict[str, type[BaseModel]] = {
    "pseudo": PseudoModel,
    "planes": PlaneModel,
    "cameras": CameraModel,
    "map": MapModel,
    "links": LinkModel,
}


def _allowed_keys(loc: tuple[int | str, ...]) -> str:
    model: type[BaseModel] = SiteModel
    if len(loc) >= 2 and loc[0] in _MODELS_BY_SECTION:
        model = _MODELS_BY_SECTION[str(loc[0])]
        if loc[0] == "map":
            if len(loc) == 3 and loc[1] == "scale":
                model = ScaleModel
        elif len(loc) == 4 and loc[0] == "cameras" and loc[2] == "calibration":
            model = CalibrationRefModel
        elif len(loc) == 5 and loc[0] == "cameras" and loc[2] == "points":
            model = PointModel
        elif len(loc) == 4 and loc[0] == "cameras" and loc[2] == "source":
            model = SourceModel
        elif len(loc) == 5 and loc[0] == "cameras" and loc[2:4] == ("source", "detector"):
            model = DetectorModel
    # Keys only cblrs writes (an export's embedded map, a pseudo site's mark) are not offered.
    keys = [key for key in model.model_fields if key not in ("image_data", "pseudo")]
    return f" (allowed: {', '.join(keys)})"


# ---------------------------------------------------------------------------- files


def read_document(path: str | Path) -> dict[str, Any]:
    """The raw mapping of a YAML or JSON site file."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SiteError(f"site file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SiteError(f"cannot read site file {path}: {error}.") from None
    return parse_document(text, path.name, json_only=path.suffix.lower() == ".json")


def parse_document(text: str, source: str, json_only: bool = False) -> dict[str, Any]:
    """A site document parsed from YAML (or JSON only), as a dict; SiteError naming ``source``
    otherwise."""
    if json_only:
        try:
            data = json.loads(text)
        except ValueError as error:
            raise SiteError(f"{source} is not valid JSON: {error}.") from None
    else:

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            mark = getattr(error, "problem_mark", None)
            where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
            problem = getattr(error, "problem", None) or "syntax error"
            raise SiteError(f"{source} is not valid YAML{where}: {problem}.") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise SiteError(f"{source}: a site file must be a mapping (version, name, planes, ...).")
    return data


def validate_document(data: dict[str, Any], source: str) -> SiteModel:
    """The validated model; the first problem raises :class:`SiteError` (see :func:`problems`)."""
    try:
        return SiteModel.model_validate(data)
    except ValidationError as error:
        raise SiteError(error_sentences(error, source, data)[0]) from None


def problems(data: dict[str, Any], source: str) -> list[str]:
    """Every schema problem of a raw document, one sentence each (empty when valid)."""
    try:
        SiteModel.model_validate(data)
    except ValidationError as error:
        return error_sentences(error, source, data)
    return []


def dump_document(data: dict[str, Any], path: str | Path) -> str:
    """Text of ``data`` as JSON (``.json``) or YAML (anything else): matrices stay on one line,
    floats keep every digit (``repr``), so reading it back gives the same numbers."""
    if Path(path).suffix.lower() == ".json":
        return json.dumps(data, indent=2) + "\n"

    class _Dumper(yaml.SafeDumper):
        pass

    def represent_list(dumper: yaml.SafeDumper, items: list) -> Any:
        flat = all(
            isinstance(item, int | float | str)
            or (isinstance(item, list) and all(isinstance(x, int | float) for x in item))
            for item in items
        )
        flat = flat and not any(isinstance(item, str) and len(item) > 40 for item in items)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", items, flow_style=flat)

    _Dumper.add_representer(list, represent_list)
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=100, allow_unicode=True)
