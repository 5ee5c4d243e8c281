"""`cblrs bench dashboard` runs end to end and reports what the browser measured."""

from __future__ import annotations

import json

import pytest

from cblrs.cli.main import main
from cblrs.dashboard.browser import browser_problem
from cblrs.runtime.broker.mosquitto_config import find_mosquitto


@pytest.mark.slow
def test_bench_dashboard_reports_browser_draw_times(tmp_path, capsys):
    problem = browser_problem()
    if problem is not None:
        pytest.skip(problem)
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")
    shot = tmp_path / "shot.png"
    code = main(["bench", "dashboard", "--tracks", "50", "--seconds", "3", "--json",
                 "--screenshot", str(shot)])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["tracks_shown"] == 50
    assert result["draws"] > 0 and result["updates_drawn_per_s"] > 0
    assert result["draw_ms_median"] is not None and result["draw_ms_median"] > 0
    assert shot.stat().st_size > 10_000


def test_bench_dashboard_bad_options_say_so(capsys):
    assert main(["bench", "dashboard", "--rate", "0"]) == 2
    assert "--rate and --seconds must be positive" in capsys.readouterr().err
