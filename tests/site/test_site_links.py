"""Sites of several planes: each camera's plane, and the links between planes."""

from __future__ import annotations

import copy
import re
from typing import Any

import numpy as np
import pytest
import yaml

from cblrs.cli.main import main
from cblrs.reference import ReferenceImage
from cblrs.site import load_site
from cblrs.site.core import save_document

POSE = {"image_size": [1920, 1080], "intrinsics": [[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]],
        "rvec": [2.181662, 0, 0], "tvec": [-15.0, 3.111758, 9.503524]}
PORTALS = [[[36, 0], [40, 0], [40, 30], [36, 30]], [[60, 0], [64, 0], [64, 30], [60, 30]]]
SITE: dict[str, Any] = {
    "version": 1,
    "planes": [
        {"id": 1, "origin": [0, 0], "size": [40, 30]},
        {"id": 2, "origin": [34, 0], "size": [40, 30]},
        {"id": 3, "origin": [60, 0], "size": [40, 30], "height": 5},
    ],
    "cameras": [
        {"name": "a", **POSE, "plane": 1},
        {"name": "b", **POSE, "plane": 2},
        {"name": "c", **POSE},
    ],
    "links": [{"planes": [1, 2]}, {"planes": [2, 3], "portals": PORTALS, "transit_s": [2, 20]}],
}


def _write(tmp_path, change=None) -> Any:
    document = copy.deepcopy(SITE)
    if change is not None:
        change(document)
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def test_cameras_planes_and_links_are_read(tmp_path):
    site = load_site(_write(tmp_path))
    assert [site.camera_plane(name) for name in site.camera_names] == [1, 2, None]
    assert site.cameras_on(1) == ["a", "c"] and site.cameras_on(3) == ["c"]
    assert site.camera_planes("b").ids == [2] and site.camera_planes("c").ids == [1, 2, 3]
    overlap, portal = site.links
    assert (overlap.planes, overlap.portal, portal.planes, portal.portal) == (
        (1, 2), False, (2, 3), True)
    # The overlap band (x 34..40) widened by 3 m; the portal as written.
    assert overlap.region_of(2).contains([[33.0, 10.0], [44.0, 10.0]]).tolist() == [True, False]
    assert portal.transit_s == (2.0, 20.0) and portal.region_of(3).contains([[62.0, 5]]).all()


def test_a_camera_with_a_plane_renders_only_that_plane(tmp_path):
    path = _write(tmp_path)
    assert main(["render", "--site", str(path), "--out", str(tmp_path / "refs"), "--quiet"]) == 0
    planes = {name: ReferenceImage.load(tmp_path / "refs" / f"{name}.png").planes.ids
              for name in "abc"}
    assert planes == {"a": [1], "b": [2], "c": [1, 2, 3]}
    site = load_site(path)
    assert site.render_reference("a").planes.ids == [1]


def test_links_and_camera_planes_survive_an_export(tmp_path):
    site = load_site(_write(tmp_path))
    again = load_site(save_document(site.export(), tmp_path / "exported.yaml"))
    assert again.export() == site.export()
    assert [link.to_dict() for link in again.links] == [link.to_dict() for link in site.links]
    assert again.camera_plane("b") == 2


def test_a_site_without_links_or_camera_planes_reads_as_before(tmp_path):
    def change(document: dict) -> None:
        del document["links"]
        for camera in document["cameras"]:
            camera.pop("plane", None)

    site = load_site(_write(tmp_path, change))
    assert site.links == () and site.cameras_on(2) == ["a", "b", "c"]
    assert "links" not in site.export()


def _set(key: str, value: Any):
    def change(document: dict) -> None:
        *parents, last = re.findall(r"[^.\[\]]+", key)
        target: Any = document
        for part in parents:
            target = target[int(part)] if part.isdigit() else target[part]
        if last.isdigit():
            target[int(last)] = value
        else:
            target[last] = value

    return change


CASES = [
    ("a camera on a plane that does not exist", _set("cameras[0].plane", 9),
     r"^site\.yaml: cameras\[0\]\.plane \(a\): no plane 9 \(planes: \[1, 2, 3\]\)\.$"),
    ("a link to a plane that does not exist", _set("links[0].planes", [1, 7]),
     r"^site\.yaml: links\[0\]: no plane 7 \(planes: \[1, 2, 3\]\)\.$"),
    ("a plane linked to itself", _set("links[0].planes", [2, 2]),
     r"^site\.yaml: links\[0\]: a link joins two different planes, got 2 twice\.$"),
    ("one plane in a link", _set("links[0].planes", [2]),
     r"^site\.yaml: links\[0\]\.planes: expected 2 numbers\.$"),
    ("planes that do not overlap", _set("links[0].planes", [1, 3]),
     r"^site\.yaml: links\[0\]: planes 1 and 3 are at different heights .* give the link "
     r"portals"),
    ("the same pair twice", _set("links", [{"planes": [1, 2]}, {"planes": [2, 1]}]),
     r"^site\.yaml: links\[1\]: planes 2 and 1 are already linked by links\[0\]\.$"),
    ("one portal", _set("links[1].portals", PORTALS[:1]),
     r"^site\.yaml: links\[1\]: portals must be two polygons"),
    ("a portal of two points", _set("links[1].portals", [PORTALS[0], [[0, 0], [1, 1]]]),
     r"^site\.yaml: links\[1\]\.portals\[1\]: expected a polygon"),
    ("a portal off its plane", _set("links[1].portals", [PORTALS[0], [[0, 0], [2, 0], [1, 2]]]),
     r"^site\.yaml: links\[1\]: the portal on plane 3 has no corner on that plane"),
    ("a transit that runs backwards", _set("links[1].transit_s", [5, 1]),
     r"^site\.yaml: links\[1\]: transit_s must be \[min, max\] seconds"),
    ("an unknown link key", _set("links[0].width", 3),
     r"^site\.yaml: links\[0\]\.width: unknown key \(allowed: planes, portals, transit_s, "
     r"max_distance_m\)\.$"),
]


@pytest.mark.parametrize(("what", "change", "message"), CASES, ids=[case[0] for case in CASES])
def test_bad_links_are_one_sentence(tmp_path, capsys, what, change, message):
    path = _write(tmp_path, change)
    code = main(["render", "--site", str(path), "--out", str(tmp_path / "refs"), "--quiet"])
    error = capsys.readouterr().err.strip()
    assert code == 1
    sentence = error.removeprefix("cblrs render: error: ")
    assert "\n" not in sentence and "Traceback" not in sentence
    assert re.search(message, sentence), sentence
    assert main(["site", "check", str(path)]) == 1


def test_overlap_regions_need_overlapping_rectangles():
    from cblrs.linking import LinkError, PlaneLink
    from cblrs.plane import PlaneSpec

    with pytest.raises(LinkError, match="planes 1 and 2 do not overlap"):
        PlaneLink.overlap(PlaneSpec(1, (0, 0), 10, 10), PlaneSpec(2, (10, 0), 10, 10))
    link = PlaneLink.overlap(PlaneSpec(1, (0, 0), 10, 10), PlaneSpec(2, (8, 2), 10, 10))
    polygon = link.regions[0].polygon
    np.testing.assert_allclose(polygon.min(axis=0), [5.0, -1.0])
    np.testing.assert_allclose(polygon.max(axis=0), [13.0, 13.0])
