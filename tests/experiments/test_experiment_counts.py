"""Count accuracy: the issue's targets on WILDTRACK and the traffic world's built OD."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets.traffic import MIN_GAP_M, roundabout_traffic_world, traffic_od
from cblrs.experiments.counts import CountsSetup, relative_error, run_counts

WILDTRACK = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "wildtrack"


@pytest.mark.slow
@pytest.mark.skipif(not (WILDTRACK / "calibrations").is_dir(), reason="WILDTRACK not found")
def test_wildtrack_line_counts_meet_the_targets_with_fusion():
    result = run_counts(CountsSetup(scenes=("wildtrack",), matchers=("fusion",), seeds=(1,)))
    runs = {run["detector"]: run for run in result["scenes"]["wildtrack"]["runs"]}
    assert runs["exact"]["line_error"] <= 0.02
    assert runs["--drop 0.2 --jitter 0.05 --seed 1"]["line_error"] <= 0.05
    assert runs["exact"]["true_crossings"] > 100  # the site's lines do cut the flows


def test_the_traffic_world_truth_od_is_the_built_one_and_cars_keep_apart():
    result = run_counts(CountsSetup(scenes=("roundabout-traffic",), matchers=(), seeds=()))
    assert result["scenes"]["roundabout-traffic"]["built_od_matches_truth"]
    world = roundabout_traffic_world()
    assert sum(traffic_od(world).values()) == len(world.objects) == 30
    times = np.arange(0, world.duration_s, 0.1)
    paths = [item.path.sample(times).xy for item in world.objects]
    for index, first in enumerate(paths):
        for second in paths[index + 1:]:
            gap = np.hypot(*(first - second).T)
            assert not (gap < MIN_GAP_M - 1e-6).any()


def test_relative_error_sums_absolute_differences():
    assert relative_error([3, 1], [2, 2]) == pytest.approx(0.5)
    assert np.isnan(relative_error([1], [0]))


def test_experiment_counts_command_on_the_plaza(tmp_path, capsys):
    code = main(["experiment", "counts", "--scenes", "plaza", "--matchers", "fusion",
                 "--seeds", "1", "--out", str(tmp_path), "--json", "--quiet"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    runs = result["scenes"]["plaza"]["runs"]
    assert [run["detector"] for run in runs] == ["exact", "--drop 0.2 --jitter 0.05 --seed 1"]
    assert (tmp_path / "experiment_counts.md").exists()
    assert (tmp_path / "analytics_count_errors.png").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--scenes", "mars"], "--scenes must list some of"),
     (["--matchers", "magic"], "--matchers must list fusion and/or paper")],
)
def test_experiment_counts_rejects_bad_options(args, message, capsys):
    assert main(["experiment", "counts", *args]) == 2
    assert message in capsys.readouterr().err
