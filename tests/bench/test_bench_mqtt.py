"""``cblrs bench mqtt``: a short real run through a Mosquitto it starts on a free port."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.bench.mqtt_load import CameraClocks
from cblrs.cli.main import main
from cblrs.runtime.broker.mosquitto_config import find_mosquitto


@pytest.fixture(autouse=True)
def _need_mosquitto():
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")


def test_a_short_run_reports_what_the_matcher_stored_and_the_subscriber_saw(capsys):
    code = main(["bench", "mqtt", "--cameras", "2", "--runs", "matcher/paced", "transport/max",
                 "--repeats", "1", "--paced-seconds", "2", "--fps", "10",
                 "--max-messages", "200", "--publisher", "paho", "--json",
                 "--clock-spread-ms", "20", "--clock-jitter-ms", "2"])
    assert code == 0
    document = json.loads(capsys.readouterr().out)
    assert document["machine"]["cores"] >= 1 and document["publisher"] == "paho"
    rows = {(row["receiver"], row["rate"]): row for row in document["results"]}
    paced = rows[("matcher", "paced")]
    assert paced["messages"] == 2 * 20 and paced["received"] == paced["messages"]
    assert 0 < paced["receipt_p50_ms"] <= paced["receipt_p99_ms"] < 5000
    assert 0 < paced["subscriber_p50_ms"] < 5000
    assert document["clock_spread_ms"] == 20 and paced["clock_jitter_ms"] == 2
    # Where a group's time went: waiting for its last camera, then the path to the tracks.
    assert 0 <= paced["last_member_p50_ms"] <= paced["last_member_p99_ms"] < 5000
    assert 0 <= paced["after_last_p50_ms"] <= paced["after_last_p99_ms"] < 5000
    # ... the latter split at the group's release from the ordering buffer.
    assert 0 <= paced["to_release_p50_ms"] <= paced["to_release_p99_ms"] < 5000
    assert 0 < paced["after_release_p50_ms"] <= paced["after_release_p99_ms"] < 5000
    # The frames after each camera's first ten (the ordering knows every frame period).
    assert 0 < paced["subscriber_steady_updates"] < paced["subscriber_updates"]
    assert 0 < paced["subscriber_steady_p50_ms"] <= paced["subscriber_steady_p99_ms"] < 5000
    full_speed = rows[("transport", "max")]
    assert full_speed["received"] == full_speed["messages"] == 200
    assert full_speed["received_per_s"] > 0


def test_the_stages_run_without_a_broker(capsys):
    assert main(["bench", "mqtt", "--stages", "--cameras", "2", "--json"]) == 0
    stages = json.loads(capsys.readouterr().out)["stages"]
    assert stages[0]["cameras"] == 2 and stages[0]["decode_us_per_message"] > 0
    # The service's tracker process ran the same windows as the tracker alone: it costs at
    # least what the tracker does (CPU in clock ticks, so within a few per cent).
    alone, process = (stages[0]["tracker_alone_us_per_message"],
                      stages[0]["tracker_process_us_per_message"])
    assert 0 < alone < 1.5 * process


@pytest.mark.parametrize("runs", [["broker/paced"], ["nobody/max"]])
def test_bad_runs_are_a_usage_error(runs, capsys):
    assert main(["bench", "mqtt", "--runs", *runs]) == 2
    assert "error" in capsys.readouterr().err


def test_camera_clocks_spread_the_cameras_and_keep_each_in_order():
    same = CameraClocks().times(4, 5, 10.0, 100.0)
    assert (same == same[:, :1]).all()  # idealised: every camera stamps a frame alike
    times = CameraClocks(spread_s=0.02, jitter_s=0.002, seed=3).times(5, 200, 10.0, 100.0)
    offsets = np.median(times - (100.0 + np.arange(200)[:, None] / 10.0), axis=0)
    assert sorted(np.round(offsets, 3).tolist()) == pytest.approx([0, 0.005, 0.01, 0.015, 0.02],
                                                                  abs=1e-3)
    assert (np.diff(times, axis=0) > 0).all()  # jitter never reorders a camera's frames
    assert np.abs(times - np.round(times * 10) / 10 - offsets).max() <= 0.02 + 1e-9
    with pytest.raises(ValueError, match=">= 0"):
        CameraClocks(spread_s=-1.0)


def test_negative_clock_options_are_a_usage_error(capsys):
    assert main(["bench", "mqtt", "--clock-jitter-ms", "-1"]) == 2
    assert "--clock-jitter-ms must be >= 0" in capsys.readouterr().err


def test_by_default_cameras_have_their_own_clocks_and_full_speed_matcher_rows_time_the_tracker(
        capsys):
    code = main(["bench", "mqtt", "--cameras", "2", "--runs", "matcher/max", "--repeats", "1",
                 "--max-messages", "100", "--publisher", "paho", "--json"])
    assert code == 0
    document = json.loads(capsys.readouterr().out)
    assert document["clock_spread_ms"] == 10 and document["clock_jitter_ms"] == 2
    row = document["results"][0]
    assert row["received"] == row["messages"] == 100
    assert row["tracker_alone_per_s"] > 0 and row["tracked_per_s"] > 0
    assert row["tracker_alone_wall_per_s"] > 0  # the same, in wall time at the run's load
