"""``cblrs experiment tracking``: issue 19's cases in one table."""

from __future__ import annotations

import json

import pytest

from cblrs.cli.main import main
from cblrs.experiments.tracking import (
    Case,
    TrackingSetup,
    default_cases,
    run_tracking,
    target_met,
    tracking_report,
)


def test_default_cases_cover_the_issue_and_hold_out_checks():
    cases = default_cases()
    scenes = {case.scene for case in cases}
    assert scenes == {"roundabout", "crossroads", "crowd", "distorted", "wildtrack",
                      "multiviewx"}
    held_out = {case.scene for case in cases if case.held_out}
    assert "crossroads" in held_out and all(case.held_out for case in cases
                                            if case.scene == "crossroads")
    assert {case.boxes for case in cases} == {"exact", "sim", "real", "yolox"}
    cars = {case.size for case in cases if case.scene == "roundabout" and not case.held_out}
    assert {40, 50, 60, 30} <= cars


@pytest.mark.parametrize(("row", "target", "met"), [
    ({"predicted_ids": 40, "true_ids": 40, "od_error": 0.05, "HOTA": 90.0},
     (("ids_equal", 1.0), ("od_error", 0.05), ("HOTA", 90.0)), True),
    ({"predicted_ids": 41, "true_ids": 40, "od_error": 0.0, "HOTA": 95.0},
     (("ids_equal", 1.0),), False),
    ({"predicted_ids": 45, "true_ids": 40, "HOTA": 91.0}, (("ids_at_most", 44.0),), False),
    ({"line_error": None}, (("line_error", 0.02),), False),
    ({"HOTA": 50.0}, (), None),
])
def test_targets_are_checked_as_stated(row, target, met):
    assert target_met(row, target) is met


def test_a_small_case_runs_end_to_end_and_reports():
    case = Case("distorted", seed=3, size=8, boxes="real", box_seed=1,
                target=(("HOTA", 0.0),))
    result = run_tracking(TrackingSetup(cases=(case,)))
    row = result["rows"][0]
    assert row["true_ids"] == 8 and row["predicted_ids"] >= 1
    assert 0 < row["HOTA"] <= 100 and row["met"] is True
    assert row["od_error"] is None  # no site file for this scene
    text = tracking_report(result)
    assert "| distorted 8 people, seed 3 | realistic detector seed 1 |" in text
    assert "MVTrajecter" in text
    json.dumps(result, allow_nan=False)  # JSON-ready


def test_cli_refuses_an_unknown_scene(capsys):
    assert main(["experiment", "tracking", "--scenes", "moon"]) == 2
    assert "--scenes must list some of" in capsys.readouterr().err


def test_scenes_tracked_side_by_side_give_the_same_rows_in_the_same_order():
    # Two scenes of a few people (three and two: the rows, not the tracking, are checked),
    # the first with two kinds of boxes: two groups, so that jobs=2 runs them side by side.
    cases = (
        Case("distorted", seed=3, size=3, boxes="exact"),
        Case("distorted", seed=3, size=3, boxes="sim", box_seed=2),
        Case("distorted", seed=4, size=2, boxes="exact"),
    )
    alone = run_tracking(TrackingSetup(cases=cases))["rows"]
    side_by_side = run_tracking(TrackingSetup(cases=cases), jobs=2)["rows"]

    def without_time(rows):
        return [{key: value for key, value in row.items() if key != "seconds"} for row in rows]

    assert [row["scene"] for row in side_by_side] == [
        "distorted 3 people, seed 3", "distorted 3 people, seed 3", "distorted 2 people, seed 4"]
    assert without_time(side_by_side) == without_time(alone)


def test_cli_refuses_no_jobs(capsys):
    assert main(["experiment", "tracking", "--scenes", "distorted", "--jobs", "0"]) == 2
    assert "--jobs must be at least 1" in capsys.readouterr().err
