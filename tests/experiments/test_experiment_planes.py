"""``cblrs experiment planes`` on a small street: the tables and the targets' figures."""

from __future__ import annotations

import json
import math

from cblrs.cli.main import main
from cblrs.experiments.planes import planes_report


def test_linking_restores_the_identities_the_planes_cut(tmp_path, capsys):
    code = main(["experiment", "planes", "--seed", "1", "--seeds", "", "--people", "7",
                 "--cars", "2", "--spawn", "3", "--max-trip", "90", "--fps", "5",
                 "--out", str(tmp_path), "--json", "--quiet"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert (tmp_path / "experiment_planes.md").read_text().strip() == planes_report(
        result).strip()
    world = result["world"]
    assert world["planes"] == 4 and world["cameras"] == 16
    assert world["objects_on_several_planes"] >= 4 and world["truth_od_equals_built"]
    [case] = result["cases"]
    single = case["single_plane"]["idf1_pooled"]
    # Without linking every plane crossing is a new identity; with it, none is.
    assert case["unlinked"]["IDF1"] < single - 10
    assert case["linked"]["IDF1"] >= 0.95 * single
    assert case["linked"]["ids"] == case["true_ids"] and case["handovers"]["overlap"] >= 4
    assert math.isfinite(case["od_error"]) and case["od_error"] < case["unlinked_od_error"]
    text = planes_report(result)
    assert "AI City 2024 protocol" in text and "`cblrs experiment planes`" in text


def test_bad_options_are_one_sentence(capsys):
    assert main(["experiment", "planes", "--drop", "2"]) == 2
    assert "--drop must lie in [0, 1]" in capsys.readouterr().err
    assert main(["experiment", "planes", "--fps", "0"]) == 2
    assert "--max-trip and --fps must be > 0" in capsys.readouterr().err
