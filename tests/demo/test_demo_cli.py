"""`cblrs demo` end to end: files, sane scores, the roundabout hand-over."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets.aicity import read_tracks
from cblrs.datasets.presets import make_scene

SCORES = {"HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1"}


@pytest.fixture(scope="module")
def roundabout_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    code = main(["demo", "--no-live", "--out", str(out), "--preset", "roundabout", "--quiet"])
    return code, out


def test_demo_writes_every_promised_file(roundabout_run, capsys):
    code, out = roundabout_run
    assert code == 0
    scene_dir = out / "roundabout"
    expected = [
        out / "metrics.json",
        scene_dir / "metrics.json",
        scene_dir / "trajectories.png",
        scene_dir / "overlay_A.png",
        scene_dir / "overlay_B.png",
        scene_dir / "references" / "A.png",
        scene_dir / "references" / "B.png",
        scene_dir / "tracks_paper.txt",
        scene_dir / "tracks_fusion.txt",
        scene_dir / "ground_truth.txt",
    ]
    missing = [str(path) for path in expected if not path.is_file()]
    assert not missing
    for name in ("trajectories.png", "overlay_A.png", "overlay_B.png"):
        image = cv2.imread(str(scene_dir / name))
        assert image is not None and image.std() > 10, name
    overlay = cv2.imread(str(scene_dir / "overlay_A.png"))
    assert overlay.shape == (720, 1280, 3)
    # The reference PNGs are real 16-bit reference images that load again.
    from cblrs.reference import ReferenceImage

    reference = ReferenceImage.load(scene_dir / "references" / "A.png")
    assert reference.bits == 16 and reference.coverage() > 0.5


def test_demo_metrics_are_sane_and_fusion_keeps_the_car(roundabout_run):
    _, out = roundabout_run
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"roundabout"}
    assert set(metrics["roundabout"]) == {"paper", "fusion"}
    for scores in metrics["roundabout"].values():
        assert set(scores) == SCORES
        assert all(0 <= scores[key] <= 100 for key in SCORES - {"MOTA"})
    # Acceptance: the car keeps one identity through both hand-overs with fusion.
    scene = make_scene("roundabout")
    tracks = read_tracks(out / "roundabout" / "tracks_fusion.txt")
    assert np.unique(tracks.track_id).tolist() == [int(tracks.track_id[0])]
    truth = scene.ground_truth
    covered = np.isin(truth.frame, tracks.frame)
    assert covered.mean() > 0.9
    # the one track follows the car all the way round (within 2 m, the evaluation's reach)
    truth_xy = {int(f): xy for f, xy in zip(truth.frame, truth.world_xy, strict=True)}
    error = [np.hypot(*(xy - truth_xy[int(f)])) for f, xy in
             zip(tracks.frame, tracks.world_xy, strict=True)]
    assert np.max(error) < 2.0
    angles = np.unwrap([np.arctan2(xy[1], xy[0]) for xy in tracks.world_xy])
    assert angles.max() - angles.min() > 1.9 * np.pi
    # and the scene really did hand the car over twice (A -> both -> B -> both -> A)
    per_scene = json.loads((out / "roundabout" / "metrics.json").read_text())
    assert per_scene["predicted_ids"]["fusion"] == 1
    assert per_scene["ground_truth_ids"] == 1


def test_demo_json_on_a_short_plaza(tmp_path, capsys):
    code = main(["demo", "--out", str(tmp_path), "--preset", "plaza", "--duration", "6",
                 "--quiet", "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    plaza = report["scenes"]["plaza"]
    assert plaza["cameras"] == 4 and plaza["frames"] == 30
    assert plaza["ground_truth_ids"] >= 20
    fusion, paper = plaza["metrics"]["fusion"], plaza["metrics"]["paper"]
    assert fusion["HOTA"] > paper["HOTA"]
    assert fusion["HOTA"] > 70
    assert plaza["predicted_ids"]["fusion"] <= plaza["predicted_ids"]["paper"]
    assert sorted(p.name for p in (tmp_path / "plaza").glob("overlay_*.png")) == [
        "overlay_NE.png", "overlay_NW.png", "overlay_SE.png", "overlay_SW.png"
    ]


def test_demo_prints_a_table_and_the_files_with_geometric_targeting(tmp_path, capsys):
    code = main(["demo", "--no-live", "--out", str(tmp_path), "--preset", "roundabout",
                 "--frames", "0:20", "--targeting", "geometric", "--quiet"])
    assert code == 0
    printed = capsys.readouterr().out
    header = printed.splitlines()[0].split()
    assert header[:8] == ["scene", "matcher", "HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1"]
    assert "roundabout    paper" in printed and "roundabout   fusion" in printed
    assert str(tmp_path / "roundabout" / "trajectories.png") in printed
    scene = json.loads((tmp_path / "roundabout" / "metrics.json").read_text())
    assert scene["targeting"] == "geometric" and scene["frames"] == 21
    # The fitted targets sit near the car's footprint centre (box targeting: about 0.9 m off).
    tracks = read_tracks(tmp_path / "roundabout" / "tracks_paper.txt")
    truth = make_scene("roundabout").ground_truth
    truth_xy = {int(f): xy for f, xy in zip(truth.frame, truth.world_xy, strict=True)}
    error = [np.hypot(*(xy - truth_xy[int(f)])) for f, xy in
             zip(tracks.frame, tracks.world_xy, strict=True)]
    assert np.median(error) < 0.5


def test_demo_on_real_data(wildtrack_root, tmp_path, capsys):
    code = main(["demo", "--dataset", str(wildtrack_root), "--frames", "0:45", "--out",
                 str(tmp_path), "--quiet", "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    (name, scene), = report["scenes"].items()
    assert scene["cameras"] == 7 and scene["frames"] == 10
    assert scene["metrics"]["fusion"]["HOTA"] > 50
    assert len(list((tmp_path / name).glob("overlay_*.png"))) == 7
    assert (tmp_path / name / "trajectories.png").is_file()


def test_demo_output_folder_that_is_a_file(tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    assert main(["demo", "--out", str(target), "--quiet"]) == 1
    assert f"cannot create the output folder {target}" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--duration", "-1"], "--duration must be a positive number of seconds, got -1.0."),
        (["--frames", "9"], "frame range '9' must be FIRST:LAST"),
        (["--frames", "5000:6000", "--preset", "roundabout"], "no frames in 5000:6000"),
        (["--dataset", "/nonexistent/cblrs"], "/nonexistent/cblrs"),
    ],
)
def test_demo_user_errors_are_one_sentence(arguments, message, tmp_path, capsys):
    code = main(["demo", "--out", str(tmp_path), "--quiet", *arguments])
    assert code in (1, 2)
    error = capsys.readouterr().err
    assert message in error
    assert "Traceback" not in error and error.count("\n") == 1
