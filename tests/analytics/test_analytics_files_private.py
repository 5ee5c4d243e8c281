"""``cblrs analytics`` and ``cblrs link --analytics`` write files of people's movements
(``crossings.csv``: each crossing's track, time and position; ``visits.csv``: each track's
visits): like track files they are their owner's alone (0600, a new folder 0700), also when
an older run left them open to others."""

from __future__ import annotations

import stat

from analytics_helpers import random_tracks

from cblrs.analytics import AnalyticsConfig, HeatmapGrid, analyse_tracks, write_result


def mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_analytics_files_are_readable_by_their_owner_only(tmp_path, square_places):
    config = AnalyticsConfig(heatmap=HeatmapGrid.covering((-8, -8, 8, 8), 1.0))
    result = analyse_tracks(random_tracks(3), square_places, config)
    assert result.crossings and result.visits  # the files hold people's movements
    out = tmp_path / "out"
    written = write_result(result, out)
    assert mode(out) == 0o700
    old = out / "crossings.csv"
    old.chmod(0o644)
    written_again = write_result(result, out)
    assert written == written_again and {path.name for path in written} >= {
        "crossings.csv", "visits.csv", "heatmap.csv", "analytics.json"}
    for path in written:
        assert mode(path) == 0o600, (path.name, oct(mode(path)))
    assert old.read_text().startswith("timestamp_s,line,track_id")
