"""``cblrs bench camera`` and ``bench detect`` on the real MultiviewX frames."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.bench.camera_cost import benchmark_camera, camera_report
from cblrs.bench.detection import HEIGHT_BINS, box_recall
from cblrs.cli.main import main
from cblrs.detections import Detections


def test_camera_cost_on_one_real_frame(multiviewx_real_root, yolox_model):
    result = benchmark_camera(multiviewx_real_root, yolox_model, repeats=1, frames=1)
    assert result["images"] == 6
    whole, tiled = result["modes"]["whole frame"], result["modes"]["tiled"]
    assert whole["inferences_per_frame"] == 1 and tiled["inferences_per_frame"] >= 3
    for mode in (whole, tiled):
        assert mode["ms"]["detect"] > mode["ms"]["targeting + lookup"] > mode["ms"]["lookup alone"]
        assert 0 < mode["lookup_share"] < 0.01
        assert mode["camera_step_ms"] > mode["ms"]["detect"]
    text = camera_report(result)
    assert "share of the colour lookup in the step" in text and "| tiled |" in text


def test_box_recall_counts_one_to_one_matches_by_height():
    truth = Detections(np.array([[0, 0, 10, 50], [100, 0, 110, 120], [200, 0, 210, 400]], float))
    found = Detections(np.array([[0, 0, 10, 48], [1, 1, 10, 50], [200, 0, 212, 390]], float))
    recall, by_height = box_recall([[truth]], [[found]])
    assert recall == pytest.approx(2 / 3)
    assert len(by_height) == len(HEIGHT_BINS) - 1
    assert by_height[0] == 1.0 and by_height[1] == 0.0 and by_height[-1] == 1.0
    assert by_height[2] is None


def test_bench_needs_a_data_set_with_images(tmp_path, capsys):
    code = main(["bench", "detect", "--dataset", str(tmp_path)])
    assert code == 2 and "holds no Image_subsets/ folder" in capsys.readouterr().err
