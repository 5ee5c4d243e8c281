"""Calibration readers: WILDTRACK/MultiviewX XML, AI City 2024 JSON, and cblrs JSON.

All readers return :class:`cblrs.camera.Camera` objects in metres, whatever unit the files
use (WILDTRACK stores centimetres), described so that the ground each camera sees lies in
front of it: a left-handed calibration (MultiviewX) is converted, with one warning
(:func:`orient_cameras`).

The cblrs JSON format (one camera per file, or ``{"cameras": [...]}``) takes one of three
forms, all in metres::

    {"name": "cam1", "image_size": [1920, 1080], "homography": [[...], [...], [...]]}
    {"name": "cam1", "image_size": [1920, 1080], "intrinsics": [[...]], "distortion": [...],
     "rvec": [...] | "rotation": [[...]], "tvec": [...], "height_axis": 1 | -1}
    {"name": "cam1", "image_size": [1920, 1080], "position": [x, y, z],
     "pan_deg": 90, "tilt_deg": 30, "roll_deg": 0, "focal_px": 1200}
"""

from __future__ import annotations

import json
import logging
import re
import xml.etree.ElementTree as ElementTree
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.errors import CalibrationError
from cblrs.handedness import orient_to_ground

logger = logging.getLogger(__name__)

WILDTRACK_CAMERAS = ("CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3")
WILDTRACK_IMAGE_SIZE = (1920, 1080)
MULTIVIEWX_IMAGE_SIZE = (1920, 1080)

# Annotated ground areas (x0, y0, width, length) in metres: WILDTRACK's 480 x 1440 grid of
# 2.5 cm cells starting at (-3 m, -9 m); MultiviewX's 1000 x 640 grid starting at the origin.
WILDTRACK_GROUND = (-3.0, -9.0, 12.0, 36.0)
MULTIVIEWX_GROUND = (0.0, 0.0, 25.0, 16.0)


def orient_cameras(
    cameras: Sequence[Camera],
    source: str | Path,
    area: tuple[float, float, float, float] | None = None,
) -> list[Camera]:
    """Cameras described so that the ground each one sees lies in front of it.

    Left-handed calibrations (every MultiviewX camera) are converted to their equivalent
    right-handed, proper-rotation form (:func:`cblrs.handedness.orient_to_ground`), and one
    warning names the converted cameras.

    Args:
        cameras: the cameras as read.
        source: the file or folder they came from (for the warning).
        area: the ground rectangle (x0, y0, width, length metres) they look at, if known.
    """
    oriented, converted = [], []
    for camera in cameras:
        camera, changed = orient_to_ground(camera, area)
        oriented.append(camera)
        if changed:
            converted.append(camera.name)
    if converted:
        logger.warning(
            "%s: camera%s %s %s calibrated in a left-handed world (the ground lies behind the "
            "camera in the published extrinsics); using the equivalent right-handed "
            "description with the height axis mirrored, which projects every point to the "
            "same pixel.",
            source,
            "s" if len(converted) > 1 else "",
            ", ".join(converted),
            "are" if len(converted) > 1 else "is",
        )
    return oriented


def read_opencv_matrices(path: str | Path, names: tuple[str, ...]) -> dict[str, NDArray]:
    """Read named matrices from an OpenCV FileStorage XML/YAML file.

    Handles both proper ``type_id="opencv-matrix"`` nodes and the bare whitespace-separated
    numbers WILDTRACK's extrinsic files use (``<rvec>1.7 0.4 -0.3</rvec>``), which OpenCV
    does not read as matrices. Missing names are left out of the result.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist.")
    plain = _read_plain_opencv_xml(path, names)
    if plain is not None:
        return plain
    import cv2  # lazy: only files beyond the plain XML form above need OpenCV's reader

    found: dict[str, NDArray] = {}
    storage = None
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        # OpenCV rejects XML without its header (SystemError from the binding); the plain
        # XML reader below still reads such files.
        storage = None
    if storage is not None and storage.isOpened():
        for name in names:
            node = storage.getNode(name)
            if node.empty() or node.isNone():
                continue
            if node.isMap():
                try:
                    matrix = node.mat()
                except cv2.error:
                    matrix = None
                if matrix is not None:
                    found[name] = np.asarray(matrix, dtype=np.float64)
                continue
            if node.isSeq():
                items = [node.at(i) for i in range(node.size())]
                # A text item reads as DBL_MAX through real(); refuse it instead.
                if not all(item.isReal() or item.isInt() for item in items):
                    raise CalibrationError(f"{path}: {name} holds non-numeric values.")
                found[name] = np.array([item.real() for item in items], dtype=np.float64)
                continue
            if node.isString():
                values = _parse_numbers(node.string(), path, name)
                if values is not None:
                    found[name] = values
            elif node.isReal() or node.isInt():
                found[name] = np.array([node.real()])
        storage.release()
    missing = [name for name in names if name not in found]
    if missing and path.suffix.lower() == ".xml":
        try:
            root = ElementTree.parse(path).getroot()
        except ElementTree.ParseError as error:
            raise CalibrationError(f"{path} is not valid XML: {error}.") from None
        for name in missing:
            element = root.find(name)
            if element is None:
                continue
            data = element.find("data")
            text = data.text if data is not None else element.text
            values = _parse_numbers(text or "", path, name)
            if values is None:
                continue
            rows, cols = element.find("rows"), element.find("cols")
            if rows is not None and cols is not None:
                values = values.reshape(int(rows.text or 0), int(cols.text or 0))
            found[name] = values
    return found


# A number as OpenCV's XML storage writes it: digits first (``1.``, ``-2.5e-06``); integers of
# at most nine digits (OpenCV reads integers as 32-bit).
_PLAIN_NUMBER = re.compile(r"[-+]?(?:\d{1,9}|\d+\.\d*(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+)")


def _read_plain_opencv_xml(path: Path, names: tuple[str, ...]) -> dict[str, NDArray] | None:
    """What :func:`read_opencv_matrices` reads from an OpenCV XML file in its plain form,
    without OpenCV; None for any other file (which then goes to OpenCV's reader).

    The plain form is what OpenCV writes, and WILDTRACK's and MultiviewX's files are: the
    ``<?xml`` header, an ``opencv_storage`` root, and each name found at most once as either
    an ``opencv-matrix`` of doubles (rows, cols, ``dt`` d, data) or an element holding
    numbers only (WILDTRACK's ``<rvec>1.7 0.4 -0.3</rvec>``). Numbers are parsed by Python's
    ``float``, correctly rounded as OpenCV's ``strtod`` is, so the values are OpenCV's bit for
    bit (tested on both data sets' files). This spares ``cblrs track`` the import of OpenCV.
    """
    if path.suffix.lower() != ".xml":
        return None
    try:
        data = path.read_bytes()
        if not data.lstrip().startswith(b"<?xml"):
            return None
        root = ElementTree.fromstring(data)
    except (OSError, ElementTree.ParseError):
        return None
    if root.tag != "opencv_storage":
        return None
    found: dict[str, NDArray] = {}
    for name in names:
        elements = root.findall(name)
        if not elements:
            continue
        if len(elements) > 1:
            return None
        element = elements[0]
        children = {child.tag: (child.text or "").strip() for child in element}
        if not children:
            text = element.text
        elif (element.attrib == {"type_id": "opencv-matrix"} and len(element) == 4
              and set(children) == {"rows", "cols", "dt", "data"} and children["dt"] == "d"
              and children["rows"].isdigit() and children["cols"].isdigit()):
            text = children["data"]
        else:
            return None
        if element.attrib and not children:
            return None
        tokens = (text or "").split()
        if not tokens or not all(_PLAIN_NUMBER.fullmatch(token) for token in tokens):
            return None
        values = np.array([float(token) for token in tokens], dtype=np.float64)
        if children:
            rows, cols = int(children["rows"]), int(children["cols"])
            if rows * cols != len(values):
                return None
            values = values.reshape(rows, cols)
        found[name] = values
    return found


def _parse_numbers(text: str, path: Path, name: str) -> NDArray | None:
    tokens = re.split(r"[\s,]+", text.strip())
    tokens = [token for token in tokens if token]
    if not tokens:
        return None
    try:
        return np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError:
        raise CalibrationError(f"{path}: {name} holds non-numeric values.") from None


def read_opencv_camera(
    name: str,
    intrinsic_path: str | Path,
    extrinsic_path: str | Path,
    image_size: tuple[int, int],
    unit_to_metres: float = 1.0,
    use_distortion: bool = True,
) -> Camera:
    """One camera from an intrinsic and an extrinsic OpenCV file.

    Args:
        unit_to_metres: scale of the extrinsic translation (0.01 for centimetres).
        use_distortion: False ignores the distortion coefficients (for undistorted frames).
    """
    intrinsic = read_opencv_matrices(intrinsic_path, ("camera_matrix", "distortion_coefficients"))
    extrinsic = read_opencv_matrices(extrinsic_path, ("rvec", "tvec"))
    if "camera_matrix" not in intrinsic:
        raise CalibrationError(f"{intrinsic_path} has no camera_matrix.")
    for key in ("rvec", "tvec"):
        if key not in extrinsic:
            raise CalibrationError(f"{extrinsic_path} has no {key}.")
    matrix = intrinsic["camera_matrix"]
    if matrix.size != 9:
        raise CalibrationError(
            f"{intrinsic_path}: camera_matrix must be 3x3, got {matrix.size} values."
        )
    rvec, tvec = extrinsic["rvec"].ravel(), extrinsic["tvec"].ravel()
    if rvec.size != 3 or tvec.size != 3:
        raise CalibrationError(f"{extrinsic_path}: rvec and tvec must have 3 values each.")
    distortion = intrinsic.get("distortion_coefficients")
    if distortion is None or not use_distortion:
        distortion = np.zeros(0)
    return Camera.from_extrinsics(
        name,
        matrix.reshape(3, 3),
        rvec,
        tvec * unit_to_metres,
        image_size,
        distortion=distortion.ravel(),
    )


def read_wildtrack_cameras(root: str | Path, distorted: bool = False) -> list[Camera]:
    """The seven WILDTRACK cameras, in view order (viewNum 0..6), in metres.

    Args:
        root: the dataset folder (with ``calibrations/``).
        distorted: use ``intrinsic_original`` (lens distortion, for the raw video) instead of
            ``intrinsic_zero`` (for the undistorted frames the annotations refer to).
    """
    root = Path(root)
    calibrations = root / "calibrations"
    if not calibrations.is_dir():
        raise CalibrationError(f"{root} has no calibrations/ folder.")
    intrinsic_dir = calibrations / ("intrinsic_original" if distorted else "intrinsic_zero")
    cameras = [
        read_opencv_camera(
            name,
            intrinsic_dir / f"intr_{name}.xml",
            calibrations / "extrinsic" / f"extr_{name}.xml",
            WILDTRACK_IMAGE_SIZE,
            unit_to_metres=0.01,
            use_distortion=distorted,
        )
        for name in WILDTRACK_CAMERAS
    ]
    return orient_cameras(cameras, root, WILDTRACK_GROUND)


def read_multiviewx_cameras(root: str | Path, use_distortion: bool = True) -> list[Camera]:
    """MultiviewX's cameras ``Camera1..CameraN`` in view order; translations are metres.

    MultiviewX's world comes from Unity and is left-handed: in the published extrinsics the
    ground every camera sees lies behind it. The cameras are returned in the equivalent
    right-handed form (see :func:`orient_cameras`), with a warning.
    """
    root = Path(root)
    intrinsic_dir = root / "calibrations" / "intrinsic"
    paths = sorted(
        intrinsic_dir.glob("intr_Camera*.xml"),
        key=lambda path: int(re.sub(r"\D", "", path.stem) or 0),
    )
    if not paths:
        raise CalibrationError(f"{intrinsic_dir} has no intr_Camera*.xml files.")
    cameras = []
    for path in paths:
        name = path.stem.removeprefix("intr_")
        cameras.append(
            read_opencv_camera(
                name,
                path,
                root / "calibrations" / "extrinsic" / f"extr_{name}.xml",
                MULTIVIEWX_IMAGE_SIZE,
                unit_to_metres=1.0,
                use_distortion=use_distortion,
            )
        )
    return orient_cameras(cameras, root, MULTIVIEWX_GROUND)


def read_aicity_calibration(
    path: str | Path, name: str | None = None, image_size: tuple[int, int] = (1920, 1080)
) -> Camera:
    """An AI City Challenge 2024 ``calibration.json``.

    Uses the "homography matrix" (world metres -> pixel). When "camera projection matrix"
    (3x4) is present it is decomposed into K, R, t so planes above the ground work too.
    """
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: an AI City calibration must be a JSON object.")
    name = name or path.parent.name or path.stem
    try:
        size = (
            int(data.get("image_size", image_size)[0]),
            int(data.get("image_size", image_size)[1]),
        )
    except (TypeError, ValueError, IndexError):
        raise CalibrationError(f"{path}: image_size must be [width, height].") from None
    projection = data.get("camera projection matrix")
    if projection is not None:
        camera = Camera.from_projection(
            name, _matrix(projection, (3, 4), path, "camera projection matrix"), size
        )
        return orient_cameras([camera], path)[0]
    homography = data.get("homography matrix")
    if homography is None:
        raise CalibrationError(
            f"{path} has neither 'homography matrix' nor 'camera projection matrix'."
        )
    return Camera.from_homography(
        name, _matrix(homography, (3, 3), path, "homography matrix"), size
    )


def _matrix(value: object, shape: tuple[int, int], path: Path, key: str) -> NDArray:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"{path}: {key!r} must be a {shape[0]}x{shape[1]} matrix of numbers."
        ) from None
    if matrix.shape != shape:
        raise CalibrationError(
            f"{path}: {key!r} must be {shape[0]}x{shape[1]}, got shape {matrix.shape}."
        )
    return matrix


def read_camera_json(path: str | Path) -> list[Camera]:
    """cameras from a cblrs JSON file (see the module docstring for the format)."""
    path = Path(path)
    data = _read_json(path)
    items = data.get("cameras", [data]) if isinstance(data, dict) else data
    if not isinstance(items, list) or not items:
        raise CalibrationError(f"{path}: expected a camera object or {{'cameras': [...]}}.")
    return orient_cameras([camera_from_dict(item, source=str(path)) for item in items], path)


def camera_from_dict(data: dict, source: str = "<dict>") -> Camera:
    """One camera of a cblrs camera JSON (name, image_size, K, distortion, R, t; or a
    homography); CalibrationError naming ``source`` and the missing or bad field otherwise."""
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: each camera must be a JSON object.")
    try:
        name = str(data["name"])
        size = (int(data["image_size"][0]), int(data["image_size"][1]))
        if "homography" in data:
            return Camera.from_homography(name, np.asarray(data["homography"], float), size)
        if "intrinsics" in data:
            rotation = data.get("rotation", data.get("rvec"))
            if rotation is None or "tvec" not in data:
                raise CalibrationError(f"{source}: camera {name!r} needs rvec/rotation and tvec.")
            return Camera.from_extrinsics(
                name,
                np.asarray(data["intrinsics"], float),
                np.asarray(rotation, float),
                np.asarray(data["tvec"], float),
                size,
                distortion=np.asarray(data.get("distortion", []), float),
                height_axis=int(data.get("height_axis", 1)),
            )
        if "position" in data:
            x, y, z = (float(value) for value in data["position"])
            return Camera.from_pose(
                name,
                (x, y, z),
                float(data.get("pan_deg", 0.0)),
                float(data.get("tilt_deg", 0.0)),
                float(data["focal_px"]),
                size,
                roll_deg=float(data.get("roll_deg", 0.0)),
                distortion=np.asarray(data.get("distortion", []), float),
            )
    except (KeyError, IndexError, TypeError, ValueError) as error:
        raise CalibrationError(f"{source}: invalid camera entry ({error}).") from None
    raise CalibrationError(
        f"{source}: camera {data.get('name')!r} needs 'homography', 'intrinsics' or 'position'."
    )


def camera_to_dict(camera: Camera) -> dict:
    """The cblrs JSON form of a camera (full parameters when known, else the homography)."""
    data: dict = {"name": camera.name, "image_size": list(camera.image_size)}
    if camera.has_pose:
        assert camera.intrinsics is not None and camera.rotation is not None
        assert camera.translation is not None
        data["intrinsics"] = camera.intrinsics.tolist()
        data["distortion"] = camera.distortion.tolist()
        import cv2  # lazy: see read_opencv_matrices

        data["rvec"] = cv2.Rodrigues(camera.rotation)[0].ravel().tolist()
        data["tvec"] = camera.translation.tolist()
        if camera.height_axis != 1:
            data["height_axis"] = camera.height_axis
    else:
        data["homography"] = camera.homography.tolist()
    return data


def calibration_layout(path: str | Path) -> str:
    """What kind of calibration ``path`` holds, without reading it.

    Returns:
        "wildtrack", "multiviewx", "aicity" (a folder of ``*/calibration.json`` or one such
        file) or "json" (any other file, read as cblrs camera JSON); "unknown" for a folder
        with none of these.
    """
    path = Path(path)
    if path.is_dir():
        if (path / "calibrations" / "extrinsic" / "extr_CVLab1.xml").is_file():
            return "wildtrack"
        if list((path / "calibrations" / "intrinsic").glob("intr_Camera*.xml")):
            return "multiviewx"
        if list(path.glob("*/calibration.json")):
            return "aicity"
        return "unknown"
    if path.name == "calibration.json":
        return "aicity"
    return "json"


def default_ground(path: str | Path) -> tuple[float, float, float, float] | None:
    """The annotated ground area ``(x0, y0, width, length)`` metres of a known layout, or None."""
    return {"wildtrack": WILDTRACK_GROUND, "multiviewx": MULTIVIEWX_GROUND}.get(
        calibration_layout(path)
    )


def read_cameras(path: str | Path, distorted: bool = False) -> list[Camera]:
    """Read cameras from any supported source, detected from what ``path`` holds.

    * a WILDTRACK folder (``calibrations/extrinsic/extr_CVLab1.xml``),
    * a MultiviewX folder (``calibrations/intrinsic/intr_Camera1.xml``),
    * an AI City ``calibration.json`` (or a scene folder with ``c*/calibration.json``),
    * a cblrs camera JSON file.
    """
    path = Path(path)
    if path.is_dir():
        if (path / "calibrations" / "extrinsic" / "extr_CVLab1.xml").is_file():
            return read_wildtrack_cameras(path, distorted=distorted)
        if list((path / "calibrations" / "intrinsic").glob("intr_Camera*.xml")):
            return read_multiviewx_cameras(path, use_distortion=True)
        calibration_files = sorted(path.glob("*/calibration.json"))
        if calibration_files:
            return [read_aicity_calibration(file) for file in calibration_files]
        raise CalibrationError(
            f"{path} is not a WILDTRACK, MultiviewX or AI City folder (no calibration files found)."
        )
    if not path.is_file():
        raise CalibrationError(f"calibration path {path} does not exist.")
    data = _read_json(path)
    aicity_keys = ("homography matrix", "camera projection matrix")
    if isinstance(data, dict) and any(key in data for key in aicity_keys):
        return [read_aicity_calibration(path)]
    return read_camera_json(path)


def _read_json(path: Path) -> dict | list:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"calibration file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise CalibrationError(f"{path} is not valid JSON: {error}.") from None
