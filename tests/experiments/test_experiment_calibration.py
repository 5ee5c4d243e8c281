"""The clicked-calibration experiment on WILDTRACK (issue 11, item 4)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.experiments.calibration import candidate_points, spread_choice


def test_spread_choice_picks_far_apart_points():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1000, (400, 2))
    chosen = spread_choice(points, 10, np.random.default_rng(1))
    assert len(set(chosen.tolist())) == 10
    gaps = np.hypot(*(points[chosen][:, None] - points[chosen][None]).T)
    np.fill_diagonal(gaps, np.inf)
    # Ten random points of the same cloud come much closer to one another.
    random = points[rng.choice(400, 10, replace=False)]
    random_gaps = np.hypot(*(random[:, None] - random[None]).T)
    np.fill_diagonal(random_gaps, np.inf)
    assert gaps.min() > 2 * random_gaps.min()
    with pytest.raises(ValueError, match="only 3 candidate points for 4"):
        spread_choice(points[:3], 4, rng)


def test_candidates_are_whole_boxes_with_their_annotated_positions(wildtrack_root):
    from cblrs.datasets import load_scene

    scene = load_scene(wildtrack_root)
    candidates = candidate_points(scene, 0, [0, 100])
    assert len(candidates["image_xy"]) > 20
    assert (candidates["image_xy"] >= 0).all() and (candidates["image_xy"] <= [1919, 1079]).all()
    # The lab calibration projects the annotated positions near the box bottoms.
    pixels, _ = scene.cameras[0].world_to_pixel(candidates["world_xy"])
    assert np.median(np.hypot(*(pixels - candidates["image_xy"]).T)) < 15


@pytest.mark.slow
def test_experiment_command_measures_clicked_against_lab(wildtrack_root, tmp_path, capsys):
    code = main(
        [
            "experiment",
            "calibration",
            "--wildtrack",
            str(wildtrack_root),
            "--counts",
            "4,10",
            "--seeds",
            "0",
            "--out",
            str(tmp_path),
            "--json",
            "--quiet",
        ]
    )
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    lab, rows = result["lab"], result["rows"]
    assert lab["scores"]["HOTA"] == pytest.approx(93.76, abs=0.05)  # README's fusion figure
    assert lab["median_error_m"] == pytest.approx(0.10, abs=0.02)
    assert [row["count"] for row in rows] == [4, 10]
    assert rows[0]["models"] == {"homography": 7}
    # WILDTRACK's frames are undistorted: k1 never predicts held-out points better.
    assert set(rows[1]["models"]) <= {"focal", "homography"}
    assert sum(rows[1]["models"].values()) == 7
    for run in result["runs"]:
        assert len(run["cameras"]) == 7 and run["located"] > 15000
    # Ten clicked points per camera localise about as well as the lab calibration.
    assert rows[1]["median_error_m"] < 0.15
    assert rows[1]["scores"]["HOTA"] > lab["scores"]["HOTA"] - 3
    assert rows[1]["held_out_m"] < 0.15
    for camera in result["runs"][1]["cameras"]:
        assert camera["held_out"] and camera["predicted_median_m"] < 0.5
    table = (tmp_path / "experiment_calibration.md").read_text()
    assert "| lab calibration |" in table and re.search(r"\| 10 \| (focal|homography) x\d", table)
    assert (tmp_path / "calibration_clicked.png").stat().st_size > 10000


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--ground-m", "0"], r"--ground-m must be a positive number, got 0\.0\."),
        (["--click-px", "-2"], r"--click-px must be a positive number, got -2\.0\."),
    ],
)
def test_experiment_refuses_a_stated_noise_that_is_not_positive(capsys, option, message):
    assert main(["experiment", "calibration", *option, "--quiet"]) != 0
    assert re.search(message, capsys.readouterr().err)
