"""``cblrs pseudo``, and ``--key`` on render, track and eval, as a user runs them."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import yaml

from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks
from cblrs.privacy import PseudoKey
from cblrs.reference import load_reference


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "site.key"
    assert main(["pseudo", "keygen", "--out", str(path)]) == 0
    return path


def test_keygen_writes_a_0600_key_and_never_replaces_one(key_file, capsys):
    assert os.stat(key_file).st_mode & 0o777 == 0o600
    first = PseudoKey.load(key_file)
    assert main(["pseudo", "keygen", "--out", str(key_file)]) == 1
    assert "exists" in capsys.readouterr().err
    assert PseudoKey.load(key_file) == first
    key_file.chmod(0o644)
    assert main(["pseudo", "site", "x.yaml", "--key", str(key_file), "--out", "y.yaml"]) == 1
    assert "accessible to others (mode 0644)" in capsys.readouterr().err


def test_track_with_a_key_tracks_as_well_and_only_the_key_maps_back(
    wildtrack_first_frames, key_file, tmp_path, capsys
):
    """On WILDTRACK's first 80 frames (HOTA 92.1 plain; 93.8 on all 200)."""
    wildtrack_root = wildtrack_first_frames(80)
    plain, pseudo = tmp_path / "plain.txt", tmp_path / "pseudo.txt"
    common = ["track", "--dataset", str(wildtrack_root), "--quiet", "--json"]
    assert main([*common, "--out", str(plain)]) == 0
    capsys.readouterr()
    assert main([*common, "--key", str(key_file), "--out", str(pseudo)]) == 0
    assert json.loads(capsys.readouterr().out)["pseudo_key_id"] == PseudoKey.load(key_file).key_id

    def score(path, *extra):
        assert main(["eval", "--dataset", str(wildtrack_root), str(path), "--json", *extra]) == 0
        return json.loads(capsys.readouterr().out)["HOTA"]

    plain_hota = score(plain)
    assert plain_hota > 90
    assert score(pseudo, "--key", str(key_file)) == pytest.approx(plain_hota, abs=0.1)
    # Without the key the pseudo tracks are nowhere near the people.
    assert score(pseudo) < 1.0
    truth = load_scene(wildtrack_root).ground_truth
    rows = read_tracks(pseudo)
    nearest = np.min(np.linalg.norm(rows.world_xy[:200, None] - truth.world_xy[None], axis=2),
                     axis=1)
    assert nearest.min() > 10.0
    # cblrs pseudo unmap gives the site tracks back.
    back = tmp_path / "back.txt"
    assert main(["pseudo", "unmap", str(pseudo), "--key", str(key_file), "--out",
                 str(back)]) == 0
    assert "rows mapped back" in capsys.readouterr().out
    assert score(back) == pytest.approx(plain_hota, abs=0.1)


def test_render_site_and_camera_refusals(wildtrack_root, key_file, tmp_path, capsys):
    site = tmp_path / "site.yaml"
    assert main(["site", "init", "--dataset", str(wildtrack_root), "--out", str(site)]) == 0
    refs = tmp_path / "refs"
    assert main(["render", "--site", str(site), "--key", str(key_file), "--out", str(refs),
                 "--quiet"]) == 0
    key = PseudoKey.load(key_file)
    reference = load_reference(refs / "CVLab1.png")
    assert reference.planes[0].origin != (-5.0, -11.0)
    pseudo_site = tmp_path / "pseudo.yaml"
    capsys.readouterr()
    assert main(["pseudo", "site", str(site), "--key", str(key_file), "--out",
                 str(pseudo_site)]) == 0
    assert "Give the matcher this file, never the key" in capsys.readouterr().out
    document = yaml.safe_load(pseudo_site.read_text())
    assert document["pseudo"] == {"key_id": key.key_id}
    assert key.secret.hex() not in pseudo_site.read_text()
    # The references and the pseudo site agree on the planes (the matcher checks this).
    assert document["planes"][0]["origin"] == list(reference.planes[0].origin)
    for command, message in [
        (["render", "--site", str(pseudo_site), "--out", str(tmp_path / "x")], "pseudo site"),
        (["pseudo", "site", str(pseudo_site), "--key", str(key_file), "--out",
          str(tmp_path / "p2.yaml")], "already a pseudo site"),
        (["track", "--dataset", str(wildtrack_root), "--site", str(pseudo_site), "--out",
          str(tmp_path / "t.txt")], "pseudo site"),
        (["eval", "--dataset", str(wildtrack_root), str(tmp_path / "t.txt"), "--site",
          str(pseudo_site)], "pseudo site"),
    ]:
        (tmp_path / "t.txt").write_text("")
        assert main(command) == 2, command
        assert message in capsys.readouterr().err
    assert main(["site", "check", str(pseudo_site)]) == 0
    report = capsys.readouterr().out
    assert f"pseudo frame of key {key.key_id}" in report and "ready for: matcher" in report
