"""Acceptance of ``cblrs track`` on real images: every MultiviewX image through the shipped
detector (YOLOX-Nano, default tiling) gives HOTA >= 75. The longest test of
test_detectors_track_cli.py, in a file of its own so that a test worker runs it beside that
file's others."""

from __future__ import annotations

import json

import pytest

from cblrs.calibration import MULTIVIEWX_GROUND
from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks
from cblrs.evaluation.metrics import evaluate


def _track(arguments: list[str], capsys) -> tuple[int, str, str]:
    code = main(["track", *arguments])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.slow
def test_track_from_real_images_with_the_shipped_detector(
    multiviewx_real_root, yolox_model, tmp_path, capsys
):
    """Acceptance: HOTA >= 75 from the real MultiviewX images (default tiling)."""
    out = tmp_path / "tracks.txt"
    code, stdout, _ = _track(
        [str(multiviewx_real_root), "--out", str(out), "--detector", "onnx",
         "--model", str(yolox_model), "--json", "--quiet"], capsys,
    )
    assert code == 0
    summary = json.loads(stdout)
    assert summary["source"] == "detector" and summary["detector"]["images"] == 60
    assert all("whole frame" in plan for plan in summary["detector"]["tiles"].values())
    scene = load_scene(multiviewx_real_root)
    metrics = evaluate(scene.ground_truth, read_tracks(out), area=MULTIVIEWX_GROUND)
    assert metrics.HOTA >= 75.0, metrics.to_dict()
