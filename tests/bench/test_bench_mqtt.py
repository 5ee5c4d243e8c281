"""``cblrs bench mqtt``: a short real run through a Mosquitto it starts on a free port."""

from __future__ import annotations

import json

import pytest

from cblrs.cli.main import main
from cblrs.runtime.broker import find_mosquitto


@pytest.fixture(autouse=True)
def _need_mosquitto():
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")


def test_a_short_run_reports_what_the_matcher_stored_and_the_subscriber_saw(capsys):
    code = main(["bench", "mqtt", "--cameras", "2", "--runs", "matcher/paced", "transport/max",
                 "--repeats", "1", "--paced-seconds", "2", "--fps", "10",
                 "--max-messages", "200", "--publisher", "paho", "--json"])
    assert code == 0
    document = json.loads(capsys.readouterr().out)
    assert document["machine"]["cores"] >= 1 and document["publisher"] == "paho"
    rows = {(row["receiver"], row["rate"]): row for row in document["results"]}
    paced = rows[("matcher", "paced")]
    assert paced["messages"] == 2 * 20 and paced["received"] == paced["messages"]
    assert 0 < paced["receipt_p50_ms"] <= paced["receipt_p99_ms"] < 5000
    assert 0 < paced["subscriber_p50_ms"] < 5000
    full_speed = rows[("transport", "max")]
    assert full_speed["received"] == full_speed["messages"] == 200
    assert full_speed["received_per_s"] > 0


def test_the_stages_run_without_a_broker(capsys):
    assert main(["bench", "mqtt", "--stages", "--cameras", "2", "--json"]) == 0
    stages = json.loads(capsys.readouterr().out)["stages"]
    assert stages[0]["cameras"] == 2 and stages[0]["decode_us_per_message"] > 0


@pytest.mark.parametrize("runs", [["broker/paced"], ["nobody/max"]])
def test_bad_runs_are_a_usage_error(runs, capsys):
    assert main(["bench", "mqtt", "--runs", *runs]) == 2
    assert "error" in capsys.readouterr().err
