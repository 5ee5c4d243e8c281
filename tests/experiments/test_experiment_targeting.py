"""Targeting experiment (section IV-B) and geometry-aware targeting."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.datasets.synthetic import project_boxes_3d
from cblrs.detections import Detections, class_id_of
from cblrs.errors import CalibrationError
from cblrs.experiments.targeting import TargetingSetup, run_targeting
from cblrs.geometric_targeting import GeometricTargeter
from cblrs.targeting import target_pixels

CAR = np.array([4.5, 1.8, 1.5])


def camera_at(tilt_deg: float) -> Camera:
    return Camera.from_pose("test", (0, 0, 8), 0, tilt_deg, 1200, (1920, 1080))


@pytest.mark.parametrize("tilt", [15, 35, 60, 85])
@pytest.mark.parametrize("yaw", [0, 45, 90, 130])
def test_geometric_targeting_recovers_the_footprint_centre(tilt, yaw):
    camera = camera_at(tilt)
    centre, _ = camera.pixel_to_world([[960.0, 640.0]])
    xyxy, visible = project_boxes_3d(camera, centre, CAR, yaw)
    # wholly in view: a box cut by the border has fewer edges than unknowns
    assert visible[0] and xyxy[0, 1] > 0 and xyxy[0, 3] < 1079
    pixels, inside = GeometricTargeter(camera).pixels_for(xyxy, CAR)
    assert inside[0]
    geometric, _ = camera.pixel_to_world(pixels)
    bottom, _ = camera.pixel_to_world(target_pixels(xyxy, 0.5, 1.0)[0])
    geometric_error = np.hypot(*(geometric - centre)[0])
    bottom_error = np.hypot(*(bottom - centre)[0])
    assert geometric_error < 0.05
    assert bottom_error > 0.3  # the bottom edge lies in front of the car


def test_target_pixels_of_detections_mixes_fallback_and_geometry():
    camera = camera_at(40)
    centres, _ = camera.pixel_to_world([[700.0, 650.0], [1300.0, 650.0]])
    xyxy, _ = project_boxes_3d(camera, centres, CAR, 30)
    detections = Detections(
        xyxy=xyxy,
        confidence=np.ones(2),
        class_id=np.array([class_id_of("car"), class_id_of("bicycle")]),
        object_id=np.array([-1, -1]),
    )
    targeter = GeometricTargeter(camera, class_sizes={"car": tuple(CAR)})
    pixels, inside = targeter.target_pixels(detections)
    assert inside.all()
    # The bicycle has no size prior here: fixed targeting (its class default) is used.
    fixed, _ = target_pixels(xyxy[1:], 0.5, 0.95, image_size=camera.image_size)
    np.testing.assert_allclose(pixels[1], fixed[0])
    ground, _ = camera.pixel_to_world(pixels[:1])
    assert np.hypot(*(ground - centres[:1])[0]) < 0.05


def test_empty_and_invalid_boxes():
    targeter = GeometricTargeter(camera_at(30))
    pixels, inside = targeter.target_pixels(Detections.empty())
    assert pixels.shape == (0, 2) and inside.shape == (0,)
    world, yaw, ok = targeter.fit(np.array([[10.0, 10.0, 5.0, 5.0], [np.nan] * 4]), CAR)
    assert not ok.any() and np.isnan(world).all() and np.isnan(yaw).all()


def test_homography_only_camera_is_refused():
    camera = Camera.from_homography("flat", camera_at(30).homography, (1920, 1080))
    with pytest.raises(CalibrationError, match="needs a posed camera"):
        GeometricTargeter(camera)


@pytest.fixture(scope="module")
def small_result():
    setup = TargetingSetup(tilts_deg=(20, 50, 90), yaws_deg=(0, 90), noise_draws=1)
    return run_targeting(setup)


def test_targeting_structure(small_result):
    assert set(small_result["aod"]) == {"exact", "noisy"}
    row = small_result["aod"]["exact"]["car"]["0"]["20"]
    assert len(row) == len(small_result["setup"]["vtps"]) == 11
    assert all(value > 0 for value in row)


def test_paper_findings_hold(small_result):
    summary = small_result["summary"]["exact"]["car"]["per_tilt"]
    best = {row["tilt_deg"]: row["best_vtp"] for row in summary}
    # The best VTP depends on tilt: lower in the box for shallow views, the centre from above.
    assert best[20] > best[50] >= best[90]
    # The bottom centre lands between camera and object at shallow and medium tilts.
    assert small_result["along_bottom"]["car"]["20"] < -1.0
    assert small_result["along_bottom"]["car"]["50"] < -1.0
    # From straight above, aiming at the bottom edge is the worst choice for a car.
    top_down = small_result["aod"]["exact"]["car"]["0"]["90"]
    assert top_down[-1] == max(top_down)


def test_geometric_beats_the_best_fixed_vtp(small_result):
    for condition in ("exact", "noisy"):
        for row in small_result["summary"][condition]["car"]["per_tilt"]:
            assert row["geometric_aod_m"] < 0.7 * row["best_vtp_aod_m"]
    for row in small_result["summary"]["exact"]["person"]["per_tilt"]:
        assert row["geometric_aod_m"] < 0.01


def test_cli_writes_figures(tmp_path, capsys):
    argv = ["experiment", "targeting", "--tilts", "30", "--yaws", "0,90", "--draws", "1"]
    argv += ["--no-wildtrack", "--out", str(tmp_path), "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert list(result["aod"]["exact"]["car"]["0"]) == ["30"]
    for name in ("targeting_car.png", "targeting_person.png", "targeting_geometric.png"):
        data = (tmp_path / name).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) < 300_000
    assert (tmp_path / "experiment_targeting.md").read_text().startswith("### Targeting")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--tilts", "abc"], "must be comma-separated numbers"),
        (["--tilts", "0"], "must lie in (0, 90]"),
        (["--draws", "0"], "--draws must be a positive integer"),
        (["--tracking", "mars"], "--tracking scenes must be wildtrack, plaza or roundabout"),
        (["--wildtrack", "/nonexistent"], "is not a WILDTRACK folder"),
    ],
)
def test_cli_errors(capsys, argv, message):
    if "--wildtrack" not in argv:
        argv = ["--no-wildtrack", *argv]
    # A folder that is not WILDTRACK is a runtime failure (1), the rest usage errors (2).
    assert main(["experiment", "targeting", *argv]) == (1 if "--wildtrack" in argv else 2)
    assert message in capsys.readouterr().err
