"""`cblrs bench tracker` and `cblrs bench pipeline`: structure and real properties."""

from __future__ import annotations

import json

import pytest

from cblrs.cli.main import main


def test_tracker_grid_and_plot(tmp_path, capsys):
    argv = ["bench", "tracker", "--tracks", "10,40", "--cameras", "1,2", "--matchers", "fusion"]
    argv += ["--frames", "4", "--repeats", "1", "--out", str(tmp_path), "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    combos = [(row["cameras"], row["live_tracks"]) for row in result["rows"]]
    assert combos == [(1, 10), (1, 40), (2, 10), (2, 40)]
    by_combo = {(row["cameras"], row["live_tracks"]): row for row in result["rows"]}
    # more tracks and more cameras mean more detections per frame
    assert by_combo[(1, 40)]["detections_per_frame"] > by_combo[(1, 10)]["detections_per_frame"]
    assert by_combo[(2, 40)]["detections_per_frame"] > by_combo[(1, 40)]["detections_per_frame"]
    assert all(row["detections_per_second"] > 0 for row in result["rows"])
    # next to the wall time, the process's CPU time: what a loaded machine does not inflate
    for row in result["rows"]:
        per_frame = row["cpu_microseconds_per_detection"] * row["detections_per_frame"] / 1000
        assert row["cpu_milliseconds_per_frame"] > 0
        assert per_frame == pytest.approx(row["cpu_milliseconds_per_frame"])
        assert 0 < row["cpu_share"]
    assert (tmp_path / "tracker_throughput.png").read_bytes().startswith(b"\x89PNG")
    assert "CPU µs/detection" in (tmp_path / "bench_tracker.md").read_text()


def test_pipeline_on_wildtrack(wildtrack_first_frames, capsys):
    """On WILDTRACK's first 40 frames (HOTA 88.8; 93.8 on all 200): the command's stages and
    a tracker that works; the reference images alone are most of the tracemalloc peak."""
    argv = ["bench", "pipeline", "--repeats", "1", "--targeting", "box"]
    argv += ["--calibration", str(wildtrack_first_frames(40)), "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["stages_seconds"]) == {"load", "render", "track", "evaluate"}
    assert result["frames"] == 40 and result["cameras"] == 7
    assert 50 < result["metrics"]["box"]["HOTA"] <= 100
    assert result["memory"]["tracemalloc_peak_bytes"] > 7 * 1920 * 1080 * 6


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["tracker", "--tracks", "a,b"], "must be comma-separated integers"),
        (["tracker", "--cameras", "0"], "values must be positive"),
        (["pipeline", "--calibration", "/nonexistent"], "needs WILDTRACK"),
        (["pipeline", "--targeting", "laser"], "--targeting must list box and/or geometric"),
    ],
)
def test_errors(capsys, argv, message):
    assert main(["bench", *argv]) == 2
    assert message in capsys.readouterr().err
