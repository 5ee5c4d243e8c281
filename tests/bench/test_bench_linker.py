"""``cblrs bench linker``: a small street through the linker alone and as a service."""

from __future__ import annotations

import json

import numpy as np

from cblrs.bench.linker import id_purity, street_load
from cblrs.cli.main import main


def test_the_load_crosses_planes_under_each_plane_s_own_ids():
    planes, per_plane, owner = street_load(planes=3, people=6, seconds=20.0, seed=1)
    assert planes.ids == [1, 2, 3]
    seen_on: dict[int, set[int]] = {}
    for (plane, _), person in owner.items():
        seen_on.setdefault(person, set()).add(plane)
    assert sum(len(on) > 1 for on in seen_on.values()) >= 3
    for plane, tracks in per_plane.items():
        assert planes.by_id(plane).contains(tracks.world_xy).all()
        assert np.all(np.diff(tracks.timestamp) >= 0)
    assert id_purity(np.array([1, 1, 2, 2]), np.array([5, 5, 6, 7])) == 0.75


def test_the_benchmark_links_and_serves(tmp_path, capsys):
    code = main(["bench", "linker", "--planes", "3", "--people", "6", "--seconds", "15",
                 "--out", str(tmp_path), "--json", "--quiet"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    linker, served = result["linker"], result["service"]
    assert linker["rows_in"] >= linker["rows_out"] > 0 and linker["handovers"] > 0
    assert linker["id_purity"] > 0.95 and linker["rows_per_s"] > 0
    assert served["rows_out"] == linker["rows_out"] and served["updates"] > 0
    assert (tmp_path / "bench_linker.md").read_text().startswith("### Linker speed")
    assert main(["bench", "linker", "--seconds", "0"]) == 2
