"""Bad site files: each is one sentence naming the file and the item, and a non-zero exit."""

from __future__ import annotations

import copy
import re
from typing import Any

import pytest
import yaml

from cblrs.cli.main import main
from cblrs.site import SiteError, check_site, load_site

HOMOGRAPHY = [
    [-27.655779, 11.296923, 654.034389],
    [1.246776, 0.873002, 64.532068],
    [-0.020719, -0.014507, 1.0],
]
POINTS = [
    [1099.9, 288.4, 16, 0],
    [16.1, 271.4, 4, 18],
    [521.4, 599.9, 2, 2],
    [608.1, 126.2, 26, 20],
    [343.0, 329.3, 6, 10],
    [807.5, 402.0, 8, 2],
]
BASE: dict[str, Any] = {
    "version": 1,
    "name": "test",
    "planes": [{"id": 1, "origin": [-5, -5], "size": [40, 30]}],
    "cameras": [
        {"name": "a", "image_size": [1280, 720], "homography": HOMOGRAPHY},
        {"name": "b", "image_size": [1280, 720], "points": POINTS},
        {"name": "c", "image_size": [1280, 720], "homography": HOMOGRAPHY},
    ],
    "places": {"zones": [{"name": "z", "polygon": [[0, 0], [4, 0], [4, 4], [0, 4]]}]},
}


def _write(tmp_path, change) -> Any:
    document = copy.deepcopy(BASE)
    change(document)
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def _set(path: str, value: Any):
    def change(document: dict) -> None:
        *parents, last = re.findall(r"[^.\[\]]+", path)
        target: Any = document
        for part in parents:
            target = target[int(part)] if part.isdigit() else target[part]
        if last.isdigit():
            target[int(last)] = value
        else:
            target[last] = value

    return change


def _delete(path: str, key: str):
    def change(document: dict) -> None:
        target: Any = document
        for part in re.findall(r"[^.\[\]]+", path):
            target = target[int(part)] if part.isdigit() else target[part]
        del target[key]

    return change


CASES = [
    # (what, change, expected message)
    ("valid", lambda document: None, None),
    (
        "fewer than 4 points",
        _set("cameras[1].points", POINTS[:3]),
        r"^site\.yaml: cameras\[1\] \(b\)\.points: 3 points cannot calibrate a camera; a ground "
        r"homography needs at least 4",
    ),
    (
        "collinear points",
        _set("cameras[1].points", [[100 + 50 * i, 300 + 20 * i, i, 2 * i] for i in range(6)]),
        r"^site\.yaml: cameras\[1\] \(b\)\.points: the 6 world points lie on one line",
    ),
    (
        "a point behind the camera",
        _set(
            "cameras[1].points",
            [[100, 600, 0, 0], [1100, 600, 10, 0], [1000, 200, 10, 20], [300, 200, 20, 10]],
        ),
        r"^site\.yaml: cameras\[1\] \(b\)\.points: row \d .*lies behind the camera",
    ),
    (
        "a map without a scale",
        _set("map", {"image": "plan.png"}),
        r"^site\.yaml: map: a map needs a scale: give metres_per_pixel or scale",
    ),
    (
        "duplicate camera names",
        _set("cameras[2].name", "a"),
        r"^site\.yaml: cameras\[2\]\.name: duplicate camera name 'a' "
        r"\(cameras\[0\] has it too\)\.$",
    ),
    (
        "a self-intersecting zone",
        _set("places.zones[0].polygon", [[0, 0], [4, 4], [4, 0], [0, 4]]),
        r"^site\.yaml: places: zone 'z': its polygon intersects itself",
    ),
    (
        "a zero-length line",
        _set("places.lines", [{"name": "l", "start": [1, 1], "end": [1, 1]}]),
        r"^site\.yaml: places: line 'l' has zero length",
    ),
    (
        "a camera without geometry",
        _set("cameras[2]", {"name": "c", "image_size": [1280, 720]}),
        r"^site\.yaml: cameras\[2\] \(c\): no geometry: give one of calibration",
    ),
    (
        "a wrong matrix",
        _set("cameras[2].homography", [[1, 2], [3, 4]]),
        r"^site\.yaml: cameras\[2\]\.homography: expected a 3x3 matrix\.$",
    ),
    (
        "an unknown key",
        _set("cameras[0].fov", 60),
        r"^site\.yaml: cameras\[0\]\.fov: unknown key \(allowed: name, image_size",
    ),
    (
        "an unknown top-level key",
        _set("camras", []),
        r"^site\.yaml: camras: unknown key "
        r"\(allowed: version, name, planes, cameras, map, places, links, alerts, timezone, "
        r"opening_hours, camera_fps\)",
    ),
    (
        "two geometries",
        _set("cameras[0].points", POINTS),
        r"^site\.yaml: cameras\[0\] \(a\): give one geometry, not homography and points\.$",
    ),
    (
        "no image size",
        _delete("cameras[0]", "image_size"),
        r"^site\.yaml: cameras\[0\] \(a\): a camera given by homography needs image_size",
    ),
    (
        "intrinsics without tvec",
        _set(
            "cameras[0]",
            {
                "name": "a",
                "image_size": [10, 10],
                "intrinsics": [[1, 0, 5], [0, 1, 5], [0, 0, 1]],
                "rvec": [0, 0, 0],
            },
        ),
        r"^site\.yaml: cameras\[0\] \(a\): intrinsics need tvec",
    ),
    ("no version", _delete("", "version"), r"^site\.yaml: version: required key is missing\.$"),
    (
        "a later version",
        _set("version", 2),
        r"^site\.yaml: version: this cblrs reads site files of version 1\.$",
    ),
    (
        "a plane of zero size",
        _set("planes[0].size", [0, 30]),
        r"^site\.yaml: planes\[0\]: size must be positive",
    ),
    (
        "duplicate plane ids",
        _set("planes", [{"id": 1, "origin": [0, 0], "size": [1, 1]}] * 2),
        r"^site\.yaml: planes\[1\]\.id: duplicate plane id 1",
    ),
    (
        "a bad camera name",
        _set("cameras[0].name", "cam/1"),
        r"^site\.yaml: cameras\[0\]\.name: camera name 'cam/1' must be non-empty without '/'",
    ),
    (
        "map pixels without a map",
        _set("cameras[1].points_unit", "map"),
        r"^site\.yaml: cameras\[1\] \(b\)\.points_unit: points in map pixels need a map with a "
        r"scale",
    ),
    (
        "point noise for a camera not given by points",
        _set("cameras[0].ground_m", 0.1),
        r"^site\.yaml: cameras\[0\] \(a\): model, points_unit, click_px, ground_m, "
        r"left_handed and max_height_m are for cameras given by points\.$",
    ),
    (
        "a ground noise of zero",
        _set("cameras[1].ground_m", 0),
        r"^site\.yaml: cameras\[1\]\.ground_m: Input should be greater than 0\.$",
    ),
    (
        "a camera frame rate of zero",
        _set("cameras[2].fps", 0),
        r"^site\.yaml: cameras\[2\]\.fps: expected a frame rate: frames per second, a number "
        r"above 0 and at most 1000 \(got 0\)\.$",
    ),
    (
        "a camera frame rate in words",
        _set("cameras[0].fps", "ten"),
        r"^site\.yaml: cameras\[0\]\.fps: expected a frame rate: .*, e\.g\. 10 \(got 'ten'\)\.$",
    ),
    (
        "an infinite site camera frame rate",
        _set("camera_fps", float("inf")),
        r"^site\.yaml: camera_fps: expected a frame rate: .* \(got inf\)\.$",
    ),
    (
        "a site camera frame rate of yes",
        _set("camera_fps", True),
        r"^site\.yaml: camera_fps: expected a frame rate: .* \(got True\)\.$",
    ),
    (
        "a missing calibration file",
        _set("cameras[0]", {"name": "a", "calibration": "none.json"}),
        r"^site\.yaml: cameras\[0\] \(a\)\.calibration: none\.json does not exist",
    ),
    (
        "a missing points file",
        _set("cameras[1].points", "none.csv"),
        r"^site\.yaml: cameras\[1\] \(b\)\.points: none\.csv does not exist",
    ),
]


@pytest.mark.parametrize(("what", "change", "message"), CASES, ids=[case[0] for case in CASES])
def test_bad_site_files(tmp_path, capsys, what, change, message):
    path = _write(tmp_path, change)
    code = main(["render", "--site", str(path), "--out", str(tmp_path / "refs"), "--quiet"])
    error = capsys.readouterr().err.strip()
    if message is None:
        assert code == 0, error
        return
    assert code == 1
    assert error.startswith("cblrs render: error: "), error
    sentence = error.removeprefix("cblrs render: error: ")
    assert "\n" not in sentence and "Traceback" not in sentence
    assert re.search(message, sentence), sentence
    # `site check` reports the same problem and exits 1.
    assert main(["site", "check", str(path)]) == 1
    checked = capsys.readouterr().out
    assert sentence.split(": ")[1].split(" ")[0].split(".")[0] in checked


def test_the_points_stated_noise_reaches_their_fit(tmp_path):
    def change(document: dict) -> None:
        document["cameras"][1].update(click_px=1.5, ground_m=0.05)

    site = load_site(_write(tmp_path, change))
    fit = site.camera("b").fit
    assert fit is not None and (fit.noise.click_px, fit.noise.ground_m) == (1.5, 0.05)
    # Exported and read again, the noise stays with the camera.
    from cblrs.site.core import save_document

    exported = save_document(site.export(), tmp_path / "exported.yaml")
    again = load_site(exported).camera("b").fit
    assert again is not None and again.noise == fit.noise


def test_check_lists_every_schema_problem(tmp_path):
    def change(document: dict) -> None:
        document["cameras"][0]["homography"] = [[1]]
        document["cameras"][2]["fov"] = 1
        del document["version"]

    report = check_site(_write(tmp_path, change))
    assert not report["valid"]
    assert len(report["problems"]) == 3, report["problems"]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("version: 1\ncameras: [\n", r"^site\.yaml is not valid YAML \(line \d+, column \d+\)"),
        ("- 1\n- 2\n", r"^site\.yaml: a site file must be a mapping"),
    ],
)
def test_unreadable_files(tmp_path, text, message):
    path = tmp_path / "site.yaml"
    path.write_text(text)
    with pytest.raises(SiteError, match=message):
        load_site(path)


def test_missing_site_file(tmp_path):
    with pytest.raises(SiteError, match=r"site file .*nope\.yaml does not exist"):
        load_site(tmp_path / "nope.yaml")


def test_json_site_files_work_too(tmp_path):
    import json

    path = tmp_path / "site.json"
    path.write_text(json.dumps(BASE))
    assert load_site(path).camera_names == ["a", "b", "c"]
    path.write_text("{bad json")
    with pytest.raises(SiteError, match=r"^site\.json is not valid JSON"):
        load_site(path)
