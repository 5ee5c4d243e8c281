"""``cblrs link`` (offline) and the command-line mistakes of ``cblrs link`` / ``cblrs linker``."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets.aicity import read_tracks, write_tracks
from cblrs.datasets.city import city_scenes, city_site_document, street_world
from cblrs.site import save_document


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """The small city's site file and every plane's tracks as AI City files (each plane's
    ground truth under its own ids)."""
    folder = tmp_path_factory.mktemp("street")
    scenes = city_scenes(street_world(seed=1, people=8, cars=3, wanderers=0, spawn_s=5.0,
                                      max_trip_m=90.0))
    site = save_document(city_site_document(scenes.spec), folder / "street.yaml")
    files = {}
    for plane_id, scene in scenes.planes.items():
        truth = scene.ground_truth
        path = folder / f"plane{plane_id}.txt"
        write_tracks(path, replace(truth, track_id=truth.track_id * 10 + plane_id),
                     frames_per_second=10.0)
        files[plane_id] = path
    return scenes, site, files


def test_link_writes_global_tracks_handovers_and_counts(street, tmp_path, capsys):
    scenes, site, files = street
    out = tmp_path / "site.txt"
    arguments = ["link", "--site", str(site), "--out", str(out), "--handovers",
                 str(tmp_path / "handovers.csv"), "--analytics", str(tmp_path / "counts"),
                 "--json"]
    for plane_id, path in files.items():
        arguments += ["--plane", f"{plane_id}={path}"]
    assert main(arguments) == 0
    summary = json.loads(capsys.readouterr().out)
    rows = read_tracks(out, 10.0)
    truth = scenes.ground_truth
    # One global id per object: each object's rows carry one id, and no id two objects.
    assert summary["global_ids"] == len(np.unique(truth.track_id))
    assert summary["rows"] == len(rows) == len(truth)
    assert set(summary["handovers"]) == {"overlap", "portal"}
    lines = (tmp_path / "handovers.csv").read_text().splitlines()
    assert lines[0].startswith("global_id,") and len(lines) == 1 + sum(
        summary["handovers"].values())
    assert summary["analytics"]["lost_after_s"] == 31.0
    assert (tmp_path / "counts" / "od.csv").is_file()
    od = {(origin, destination): value for origin, row in summary["analytics"]["od"].items()
          for destination, value in row.items() if value}
    assert od == dict(scenes.spec.true_od())


@pytest.mark.parametrize(
    ("arguments", "code", "message"),
    [
        (["link", "--out", "x.txt", "--plane", "1"], 2, "--plane '1' must be ID=FILE"),
        (["link", "--out", "x.txt"], 2, "give every plane's tracks with --plane"),
        (["link", "--out", "x.txt", "--plane", "1=a.txt", "--plane", "1=b.txt"], 2,
         "--plane 1 is given twice"),
        (["link", "--out", "x.txt", "--plane", "1=missing.db"], 1, "missing.db does not exist"),
        (["link", "--out", "x.txt", "--plane", "9=PLANE1"], 1, "the site has no plane 9"),
        (["linker", "--db", "x.db"], 2, "give --site SITE and --db FILE"),
        (["linker", "--site", "SITE", "--db", "x.db", "--max-wait", "0"], 2,
         "--max-wait must be a finite number greater than 0"),
        (["linker", "--stats", "missing.db"], 1, "linker database missing.db does not exist"),
        (["linker", "--site", "SITE", "--prepare", "--backbone", "nats://127.0.0.1:9",
          "--username", "admin"], 2, "--prepare with the admin's login: give --client-id"),
    ],
)
def test_mistakes_are_one_sentence(street, tmp_path, capsys, monkeypatch, arguments, code,
                                   message):
    _, site, files = street
    monkeypatch.chdir(tmp_path)
    arguments = [item.replace("=PLANE1", f"={files[1]}") for item in arguments]
    if arguments[0] == "link" or "SITE" in arguments:
        arguments = [str(site) if item == "SITE" else item for item in arguments]
        if "--site" not in arguments:
            arguments += ["--site", str(site)]
    assert main(arguments) == code
    error = capsys.readouterr().err.strip()
    assert message in error and "\n" not in error and "Traceback" not in error, error


def test_a_site_without_links_has_nothing_to_link(street, tmp_path, capsys):
    _, site, files = street
    document = json.loads(json.dumps(city_site_document(street[0].spec)))
    del document["links"]
    plain = save_document(document, tmp_path / "plain.yaml")
    assert main(["link", "--site", str(plain), "--out", str(tmp_path / "x.txt"), "--plane",
                 f"1={files[1]}"]) == 1
    assert "has no links between its planes" in capsys.readouterr().err
    assert main(["linker", "--site", str(plain), "--db", str(tmp_path / "l.db")]) == 2
    assert "nothing to link" in capsys.readouterr().err
    assert site.is_file()
