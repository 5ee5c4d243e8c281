"""`cblrs bench lookup` and `cblrs bench render`: output structure and real properties."""

from __future__ import annotations

import json

import pytest

from cblrs.bench.lookup import METHODS, benchmark_lookup
from cblrs.cli.main import main


def run_json(capsys, *argv: str) -> dict:
    assert main(["bench", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("bits", [8, 16])
def test_lookup_structure_and_agreement(capsys, bits):
    result = run_json(capsys, "lookup", "--n", "300", "--repeats", "1", "--bits", str(bits))
    assert result["n"] == 300
    for method in METHODS:
        assert result["one_point"][method]["repeats"] == 1
        assert result["one_point"][method]["median"] > 0
        assert result["batched"][method]["ns_per_point"] > 0
    # The three localisers see the same pixels and agree within the colour cell.
    valid = result["agreement"]["valid_fraction"]
    assert abs(valid["colour"] - valid["homography"]) < 0.02
    assert valid["lut"] == valid["homography"]
    assert (
        result["agreement"]["colour_vs_homography_max_m"]
        <= result["agreement"]["half_cell_diagonal_m"] + 1e-6
    )
    sizes = result["sizes_bytes"]
    assert sizes["homography_json"] < 1000 < sizes["png_8bit"] < sizes["png_16bit"]
    assert sizes["png_16bit"] < sizes["lut_npy_float32"]
    assert sizes["lut_npy_float32"] >= 1920 * 1080 * 2 * 4
    assert result["machine"]["cores"] >= 1
    assert result["paper"]["table_i_seconds"]["i5-4690K @ 3.50GHz"]["colour"] == 0.19545


def test_lookup_text_and_files(capsys, tmp_path):
    assert main(["bench", "lookup", "--n", "100", "--repeats", "1", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "Colour (ours)" in text and "i5-4690K" in text
    saved = json.loads((tmp_path / "bench_lookup.json").read_text())
    assert saved["n"] == 100
    assert (tmp_path / "bench_lookup.md").read_text().startswith("### Table I")
    figure = (tmp_path / "lookup_table_i.png").read_bytes()
    assert figure.startswith(b"\x89PNG") and len(figure) < 300_000


def test_lookup_is_reproducible_in_its_pixels():
    first = benchmark_lookup(count=50, repeats=1, seed=3)
    second = benchmark_lookup(count=50, repeats=1, seed=3)
    assert first["agreement"] == second["agreement"]


def test_render_rows(capsys):
    result = run_json(capsys, "render", "--repeats", "1")
    combos = {(row["bits"], row["distorted"]) for row in result["rows"]}
    assert combos == {(8, False), (16, False), (8, True), (16, True)}
    for row in result["rows"]:
        assert row["warm_ms"]["median"] > 0
        assert 0.05 < row["coverage"] <= 1.0
        assert row["png_bytes"] > 0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["lookup", "--n", "0"], "--n must be a positive integer"),
        (["render", "--repeats", "-1"], "--repeats must be a positive integer"),
        (["lookup", "--calibration", "/nonexistent/folder"], "is not a WILDTRACK folder"),
    ],
)
def test_bench_errors(capsys, argv, message):
    assert main(["bench", *argv]) != 0
    assert message in capsys.readouterr().err


def test_built_in_camera_without_wildtrack(monkeypatch):
    from cblrs.bench import cameras

    monkeypatch.setattr(cameras, "find_wildtrack", lambda explicit=None: None)
    result = benchmark_lookup(count=200, repeats=1)
    assert result["camera"]["source"] == "built-in synthetic"
    assert result["agreement"]["valid_fraction"]["colour"] > 0.3
    distorted = cameras.benchmark_camera(distorted=True).camera
    assert distorted.has_distortion and distorted.image_size == (1920, 1080)
