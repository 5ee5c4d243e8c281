"""`cblrs bench claims`: each claim of the reference image, measured on small inputs."""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from cblrs.cli.main import main


@pytest.fixture(scope="module")
def claims_run(tmp_path_factory):
    """One ``cblrs bench claims`` run for the module (most of its CPU is rendering, whatever
    --n): (what it printed, its --out folder). The claims' tests read the JSON it wrote."""
    out = tmp_path_factory.mktemp("claims")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["bench", "claims", "--n", "3000", "--repeats", "1", "--seed", "1",
                     "--out", str(out)])
    assert code == 0
    return printed.getvalue(), out


@pytest.fixture(scope="module")
def claims(claims_run):
    return json.loads((claims_run[1] / "bench_claims.json").read_text())


def test_distortion_colour_is_exact_homography_is_not(claims):
    errors = claims["distortion"]["errors"]
    homography = errors["homography (ignores the lens)"]
    colour_16 = errors["colour, 16 bit"]
    colour_8 = errors["colour, 8 bit"]
    assert homography["p95_cm"] > 10.0
    assert colour_16["max_cm"] < 1.0
    step_x, step_y = claims["distortion"]["steps_m"]["8"]
    # 8 bit: within half a cell diagonal (plus a little for nearest-pixel reading).
    assert colour_8["max_cm"] <= 100 * 0.5 * (step_x**2 + step_y**2) ** 0.5 + 1.0


def test_non_planar_ground(claims):
    terraces = claims["non_planar"]["terraces"]
    assert terraces["0 m"]["homography_z0"]["max_cm"] < 0.01
    assert terraces["1 m"]["homography_z0"]["median_cm"] > 100.0
    assert terraces["1 m"]["colour_16bit"]["max_cm"] < 0.1
    ramp = claims["non_planar"]["ramp"]["errors"]
    medians = [ramp[f"colour_16bit_{strips}_strips"]["median_cm"] for strips in (1, 5, 20, 80)]
    assert medians == sorted(medians, reverse=True)
    assert medians[-1] < ramp["homography_z0"]["median_cm"] / 20


def test_several_planes(claims):
    bridge = claims["several_planes"]["bridge"]
    assert bridge["pixels_on_bridge"] > 0
    assert bridge["plane_id_correct_fraction"] > 0.999
    assert bridge["colour_16bit"]["max_cm"] < 0.1
    assert bridge["homography_z0"]["median_cm"] > 500.0
    distant = claims["several_planes"]["distant_areas"]["8 bit"]
    assert distant["two_planes"]["max_cm"] < distant["one_plane"]["median_cm"]


def test_camera_side(claims):
    rows = {
        row["method"].split(",")[0].split(" (")[0]: row for row in claims["camera_side"]["rows"]
    }
    colour = rows["colour reference"]
    assert not colour["needs_calibration"] and not colour["knows_world_coordinates"]
    assert rows["homography"]["needs_calibration"]
    assert colour["stored_bytes"] < rows["LUT"]["stored_bytes"] / 10


def test_claims_cli(claims_run):
    printed, out = claims_run
    assert "Lens distortion" in printed
    saved = json.loads((out / "bench_claims.json").read_text())
    assert saved["n"] == 3000
    figure = (out / "claims_distortion.png").read_bytes()
    assert figure.startswith(b"\x89PNG") and len(figure) < 300_000
