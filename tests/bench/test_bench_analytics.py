"""``cblrs bench analytics`` prints its figures (small sizes; speed is not asserted)."""

from __future__ import annotations

import json

from cblrs.bench.analytics import crowd_tracks
from cblrs.cli.main import main


def test_bench_analytics_runs_and_reports(capsys):
    code = main(["bench", "analytics", "--tracks", "20", "--hours", "0.01", "--online-minutes",
                 "0.1", "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["rows"] == 20 * 360 and result["online_updates"] == 60
    assert result["offline_rows_per_s"] > 0 and result["crossings"] > 0


def test_the_crowd_keeps_its_size_and_stays_on_the_square():
    tracks = crowd_tracks(tracks=30, seconds=120, rate_hz=2, life_s=20)
    assert len(tracks) == 30 * 240
    assert tracks.world_xy.min() > -1 and tracks.world_xy[:, 0].max() < 61
    assert len(set(tracks.track_id.tolist())) > 30 * 5
