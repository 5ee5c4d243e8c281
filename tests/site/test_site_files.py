"""Site files from datasets (init), as one file (export), and with datasets (scene)."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from cblrs.calibration import camera_to_dict
from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.datasets import load_scene
from cblrs.site import SiteError, check_site, dump_document, load_site, save_document
from cblrs.site.dataset import site_from_dataset

MULTIVIEWX = __import__("pathlib").Path(__file__).resolve().parents[3] / "shared/data/multiviewx"


def _same_camera(first: Camera, second: Camera) -> None:
    assert first.name == second.name and first.image_size == second.image_size
    np.testing.assert_array_equal(first.homography, second.homography)
    for name in ("intrinsics", "rotation", "translation"):
        a, b = getattr(first, name), getattr(second, name)
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.distortion, second.distortion)


def test_wildtrack_site_gives_the_datasets_cameras_and_plane(wildtrack_root, tmp_path):
    path = save_document(
        site_from_dataset(wildtrack_root, tmp_path / "site.yaml"), tmp_path / "site.yaml"
    )
    site = load_site(path)
    scene = load_scene(wildtrack_root)
    assert site.camera_names == scene.camera_names
    assert site.planes is not None and site.planes[0] == scene.plane.__class__(
        1, scene.plane.origin, scene.plane.width, scene.plane.length, 16, name="ground"
    )
    for original, resolved in zip(scene.cameras, site.cameras(), strict=True):
        _same_camera(original, resolved.camera)
        np.testing.assert_array_equal(resolved.position, original.centre)
    # The calibration is referred to, relative to the site file.
    assert "calibration" in path.read_text() and "intrinsics" not in path.read_text()


def test_export_inlines_everything_and_round_trips_exactly(wildtrack_root, example_site, tmp_path):
    # The documented site, docs/sites.md (points inline and in a CSV in map pixels, a
    # homography, a pose, a calibration file, a map image) plus WILDTRACK cameras referred to
    # by folder.
    text = example_site.read_text()
    wildtrack = site_from_dataset(wildtrack_root, example_site)["cameras"][:2]
    document = __import__("yaml").safe_load(text)
    document["cameras"] += wildtrack
    save_document(document, example_site)
    original = load_site(example_site)
    original_cameras = original.cameras()
    bundle = tmp_path / "bundle" / "site-bundle.yaml"
    assert main(["site", "export", str(example_site), "--out", str(bundle)]) == 0
    exported_text = bundle.read_text()
    for referred in ("calibrations/north.json", "clicks/east.csv", "plan.png", "wildtrack"):
        assert referred not in exported_text
    # In another folder with nothing beside it, the bundle gives the same cameras bit for bit.
    shutil.rmtree(example_site.parent / "calibrations")
    exported = load_site(bundle)
    for first, second in zip(original_cameras, exported.cameras(), strict=True):
        _same_camera(first.camera, second.camera)
        assert first.position == second.position
    assert exported.places.to_dict() == original.places.to_dict()
    assert exported.planes == original.planes
    # Exporting the export changes nothing, byte for byte; JSON too.
    assert dump_document(exported.export(), bundle) == exported_text
    as_json = tmp_path / "bundle.json"
    as_json.write_text(dump_document(exported.export(), as_json))
    for first, second in zip(exported.cameras(), load_site(as_json).cameras(), strict=True):
        _same_camera(first.camera, second.camera)
    assert main(["site", "export", str(bundle), "--out", str(bundle)]) == 2


def test_multiviewx_site_reads_through_the_dataset_reader(tmp_path):
    if not (MULTIVIEWX / "calibrations").is_dir():
        pytest.skip("MultiviewX data not found")
    path = save_document(
        site_from_dataset(MULTIVIEWX, tmp_path / "site.yaml"), tmp_path / "site.yaml"
    )
    site = load_site(path)
    assert site.camera_names == [f"Camera{index}" for index in range(1, 7)]
    assert site.planes is not None and site.planes[0].width == 29.0
    report = check_site(path)
    assert report["valid"] and all(camera["ok"] for camera in report["cameras"])
    # Every camera is distorted (the reader's lens model) and sized like the frames.
    assert all(
        camera["distorted"] and camera["image_size"] == [1920, 1080] for camera in report["cameras"]
    )


def test_aicity_site_estimates_the_plane_from_what_the_cameras_see(tmp_path):
    # No AI City data ships here: two calibration.json files in its format, written from
    # known cameras (one with a projection matrix, one with a homography only).
    scene = tmp_path / "S001"
    first = Camera.from_pose("c001", (0.0, -12.0, 8.0), 90, 35, 1000, (1920, 1080))
    second = Camera.from_pose("c002", (12.0, 25.0, 8.0), -90, 35, 1000, (1920, 1080))
    for camera, key in ((first, "camera projection matrix"), (second, "homography matrix")):
        folder = scene / camera.name
        folder.mkdir(parents=True)
        if key == "homography matrix":
            matrix = camera.homography
        else:
            assert camera.intrinsics is not None and camera.rotation is not None
            matrix = camera.intrinsics @ np.column_stack([camera.rotation, camera.translation])
        (folder / "calibration.json").write_text(json.dumps({key: matrix.tolist()}))
    path = tmp_path / "site.yaml"
    assert main(["site", "init", str(scene), "--out", str(path)]) == 0
    site = load_site(path)
    assert site.camera_names == ["c001", "c002"]
    plane = site.planes[0]
    # Both cameras look at the ground between y = -5 and y = 18 around x = 0.
    assert plane.origin[1] < 0 < 13 < plane.origin[1] + plane.length
    assert plane.origin[0] < 0 < plane.origin[0] + plane.width
    c002 = site.camera("c002")
    assert not c002.camera.has_pose
    np.testing.assert_allclose(c002.position, (12.0, 25.0, 8.0), atol=0.05)  # estimated focal
    assert "estimated focal length" in c002.position_source
    assert main(["site", "init", str(scene), "--out", str(path)]) == 2  # exists: --force


def test_init_refuses_a_folder_without_calibrations(tmp_path, capsys):
    assert main(["site", "init", str(tmp_path), "--out", str(tmp_path / "s.yaml")]) == 1
    assert "is not a WILDTRACK, MultiviewX or AI City folder" in capsys.readouterr().err


def test_site_scene_needs_every_dataset_camera(wildtrack_root, tmp_path):
    document = site_from_dataset(wildtrack_root, tmp_path / "site.yaml")
    document["cameras"] = document["cameras"][:6]
    site = load_site(save_document(document, tmp_path / "site.yaml"))
    with pytest.raises(SiteError, match=r"site\.yaml has no camera 'IDIAP3' of the dataset"):
        site.scene(load_scene(wildtrack_root))


def test_a_site_with_only_places(tmp_path, capsys):
    path = tmp_path / "places.yaml"
    path.write_text("version: 1\nplaces:\n  lines: [{name: door, start: [0, 0], end: [2, 0]}]\n")
    report = check_site(path)
    assert report["ready"]["analytics"] and not report["ready"]["render"]
    assert report["missing"]["render"] == ["no planes (planes: [{id, origin, size}])", "no cameras"]
    assert main(["site", "check", str(path), "--for", "analytics"]) == 0
    assert main(["site", "check", str(path), "--for", "analytics,render"]) == 1
    capsys.readouterr()
    assert main(["render", "--site", str(path), "--out", str(tmp_path / "r")]) == 1
    assert "places.yaml has no planes, which render needs" in capsys.readouterr().err


def test_render_track_and_eval_with_a_site(wildtrack_root, tmp_path, capsys):
    site = tmp_path / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(site), "--bits", "8"]) == 0
    assert main(["render", "--site", str(site), "--out", str(tmp_path / "refs"), "--json"]) == 0
    capsys.readouterr()
    from cblrs.reference import ReferenceImage

    reference = ReferenceImage.load(tmp_path / "refs" / "CVLab1.png")
    assert reference.bits == 8 and reference.camera_name == "CVLab1"
    tracks = tmp_path / "t.txt"
    assert (
        main(
            [
                "track",
                str(wildtrack_root),
                "--site",
                str(site),
                "--out",
                str(tracks),
                "--frames",
                "0:200",
                "--json",
            ]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["render_seconds"] > 0
    assert (
        main(["eval", str(wildtrack_root), str(tracks), "--frames", "0:200", "--site", str(site)])
        == 0
    )
    assert "scored inside site.yaml's planes" in capsys.readouterr().out
    assert main(["render", str(wildtrack_root), "--site", str(site), "--out", "x"]) == 2
    assert "give --dataset (or CALIBRATION) or --site, not both" in capsys.readouterr().err
    assert main(["demo", "--site", str(site), "--out", str(tmp_path / "d")]) == 2
    assert "--site needs --dataset" in capsys.readouterr().err


def test_camera_json_from_calibrate_is_a_site_calibration(tmp_path):
    camera = Camera.from_pose("cam", (0.0, -10.0, 6.0), 90, 30, 1000, (1280, 720))
    (tmp_path / "cam.json").write_text(json.dumps(camera_to_dict(camera)))
    (tmp_path / "site.yaml").write_text(
        "version: 1\ncameras: [{name: renamed, calibration: cam.json}]\n"
    )
    resolved = load_site(tmp_path / "site.yaml").camera("renamed")
    assert resolved.camera.name == "renamed"
    np.testing.assert_allclose(resolved.position, (0.0, -10.0, 6.0), atol=1e-9)


def test_matcher_start_up_line_says_which_cameras_have_positions(tmp_path):
    from cblrs.cli.matcher import position_summary, site_positions

    down = Camera.from_pose("down", (0.0, 0.0, 10.0), 0, 90, 1000, (1280, 720))
    tilted = Camera.from_pose("tilted", (0.0, -10.0, 6.0), 90, 30, 1000, (1280, 720))
    document = {
        "version": 1,
        "planes": [{"id": 1, "origin": [-10, -10], "size": [20, 30]}],
        "cameras": [
            {"name": "down", "image_size": [1280, 720], "homography": down.homography.tolist()},
            {"name": "tilted", "image_size": [1280, 720], "homography": tilted.homography.tolist()},
        ],
    }
    site = load_site(save_document(document, tmp_path / "site.yaml"))
    positions = site_positions(site, site.camera_names)
    assert list(positions) == ["tilted"]
    text = position_summary(site, site.camera_names, {"camera_positions": positions}, "fusion")
    assert re.search(
        r"camera positions for 1 of 2 cameras: tilted \(-?0\.00, -10\.00, 6\.00 m high\) ", text
    )
    assert "[homography + estimated focal length 1000 px]" in text
    assert "without a position: down (homography only: the focal length cannot be read" in text
    assert "none (give --site" in position_summary(None, ["a"], {}, "fusion")


def test_matcher_site_mistakes(wildtrack_root, tmp_path, capsys):
    places = tmp_path / "places.yaml"
    places.write_text(
        "version: 1\nplaces: {zones: [{name: z, polygon: [[0, 0], [1, 0], [0, 1]]}]}\n"
    )
    assert main(["matcher", "--site", str(places), "--db", str(tmp_path / "m.db")]) == 1
    assert "places.yaml has no planes, which the matcher needs" in capsys.readouterr().err
    site = tmp_path / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(site)]) == 0
    other = tmp_path / "other.yaml"
    assert (
        main(["site", "init", str(wildtrack_root), "--out", str(other), "--plane", "0,0,10,10"])
        == 0
    )
    assert main(["render", "--site", str(other), "--out", str(tmp_path / "refs"), "--quiet"]) == 0
    capsys.readouterr()
    code = main(
        [
            "matcher",
            "--site",
            str(site),
            "--references",
            str(tmp_path / "refs"),
            "--db",
            str(tmp_path / "m.db"),
        ]
    )
    assert code == 2
    assert "were rendered for other planes than site.yaml's" in capsys.readouterr().err
