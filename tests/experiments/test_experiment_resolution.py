"""`cblrs experiment resolution`: raster steps and tracking with coarser reference images."""

from __future__ import annotations

import json

import pytest

from cblrs.cli.main import main
from cblrs.datasets.presets import make_scene
from cblrs.experiments.resolution import raster_step_table, square_plane


@pytest.mark.parametrize(
    ("size", "bits", "step_cm"),
    [(50.0, 8, 19.61), (30.0, 8, 11.76), (50.0, 16, 0.0763), (1000.0, 8, 392.16)],
)
def test_raster_steps(size, bits, step_cm):
    rows = raster_step_table((size,), (bits,))
    assert rows[0]["step_cm"] == pytest.approx(step_cm, abs=0.01)
    assert rows[0]["max_error_cm"] == pytest.approx(step_cm * 2**0.5 / 2, abs=0.01)


def test_square_plane_covers_the_scene_plane():
    scene = make_scene("plaza", duration_s=1.0)
    plane = square_plane(scene, 10.0, 8)  # smaller than the scene: grown to cover it
    assert plane.width == plane.length == max(scene.plane.width, scene.plane.length)
    big = square_plane(scene, 100.0, 16)
    assert big.width == 100.0 and big.bits == 16
    x0, y0 = scene.plane.origin
    assert big.origin[0] <= x0 and big.origin[1] <= y0
    assert big.origin[0] + big.width >= x0 + scene.plane.width


def test_cli_resolution_on_a_short_synthetic_scene(tmp_path, capsys):
    argv = ["experiment", "resolution", "--scenes", "plaza", "--frames", "12", "--sizes", "500"]
    argv += ["--out", str(tmp_path), "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    rows = result["scenes"]["plaza"]["rows"]
    assert [(row["plane"], row["bits"]) for row in rows] == [
        ("scene plane", 8),
        ("scene plane", 16),
        ("500 m", 8),
        ("500 m", 16),
    ]
    by_key = {(row["plane"], row["bits"]): row for row in rows}
    # A 2 m raster (500 m at 8 bit) costs localisation accuracy; 16 bit does not.
    assert by_key[("500 m", 8)]["metrics"]["LocA"] < by_key[("500 m", 16)]["metrics"]["LocA"] - 5
    assert by_key[("scene plane", 16)]["delta_same_plane_16bit"]["HOTA"] == 0
    assert (tmp_path / "resolution.png").read_bytes().startswith(b"\x89PNG")
    assert (tmp_path / "experiment_resolution.md").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--bits", "12"], "--bits must be 8 and/or 16"),
        (["--scenes", "mars"], "--scenes must name some of"),
        (["--sizes", "-5"], "--sizes must be positive"),
        (["--frames", "0"], "--frames must be a positive integer"),
    ],
)
def test_cli_resolution_errors(capsys, argv, message):
    assert main(["experiment", "resolution", *argv]) == 2
    assert message in capsys.readouterr().err
