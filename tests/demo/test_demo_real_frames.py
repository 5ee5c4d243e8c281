"""``cblrs demo --dataset DIR --detector onnx --model M``: pictures over the real frames."""

from __future__ import annotations

import json

import cv2
import numpy as np

from cblrs.cli.main import main


def test_demo_on_real_frames(multiviewx_real_root, yolox_model, tmp_path, capsys):
    out = tmp_path / "demo"
    code = main([
        "demo", "--dataset", str(multiviewx_real_root), "--detector", "onnx",
        "--model", str(yolox_model), "--tiling", "off", "--frames", "1:3",
        "--out", str(out), "--quiet", "--json",
    ])
    assert code == 0
    report = json.loads(capsys.readouterr().out)["scenes"]["multiviewx"]
    assert report["detector"]["tiling"] == "off" and report["detector"]["images"] == 18
    assert set(report["metrics"]) == {"paper", "fusion"}
    assert report["metrics"]["fusion"]["HOTA"] > 50
    scene = out / "multiviewx"
    assert (scene / "trajectories.png").is_file()
    for number in range(1, 7):
        overlay = cv2.imread(str(scene / f"overlay_Camera{number}.png"))
        assert overlay.shape == (1080, 1920, 3)
        # Drawn over the real frame: the sky and buildings show through, not a black canvas.
        frame = cv2.imread(str(multiviewx_real_root / "Image_subsets" / f"C{number}" / "0001.jpg"))
        top = slice(60, 250)
        difference = np.abs(overlay[top].astype(int) - frame[top].astype(int)).mean()
        assert overlay[top].mean() > 60 and difference < 40


def test_demo_detector_needs_a_dataset(capsys, tmp_path):
    code = main(["demo", "--detector", "onnx", "--model", "m.onnx", "--out", str(tmp_path)])
    assert code == 2
    assert "need --dataset DIR" in capsys.readouterr().err
