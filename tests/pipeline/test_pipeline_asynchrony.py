"""Unsynchronised cameras in process: own clocks, jitter, frame rates, lost messages.

The target: with clock offsets up to ±50 ms and a few milliseconds of jitter, fusion HOTA
drops by at most 1 point against the same input synchronised (same frame rates and lost
messages), with one output row per track and frame.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks
from cblrs.datasets.clocks import ClockSimulation
from cblrs.datasets.presets import make_scene
from cblrs.evaluation import evaluate
from cblrs.pipeline import render_scene_references, track_scene


def hota(scene, result) -> float:
    return evaluate(scene.ground_truth, result.tracks, frames=result.captured_frames).HOTA


def one_row_per_frame_and_track(tracks) -> bool:
    keys = set(zip(tracks.frame.tolist(), tracks.track_id.tolist(), strict=True))
    return len(keys) == len(tracks)


@pytest.fixture(scope="module")
def wildtrack(wildtrack_root):
    scene = load_scene(wildtrack_root)
    return scene, render_scene_references(scene)


@pytest.fixture(scope="module")
def plaza():
    scene = make_scene("plaza", fps=30.0, duration_s=20.0)
    return scene, render_scene_references(scene)


@pytest.fixture(scope="module")
def plaza_synchronised_hota(plaza) -> float:
    """HOTA of the plaza at 10 and 15 fps, synchronised: the baseline of every spread (one
    run for the module; the tracker is deterministic)."""
    scene, references = plaza
    base = ClockSimulation(camera_fps=(10.0, 15.0), drop=0.1, seed=1)
    return hota(scene, track_scene(scene, references=references, clocks=base))


@pytest.mark.parametrize("seed", [0, 1])
def test_wildtrack_with_clock_offsets_of_50_ms(wildtrack, seed):
    scene, references = wildtrack
    base = ClockSimulation(drop=0.1, seed=seed)
    offsets = ClockSimulation(offset_s=0.05, jitter_s=0.003, drop=0.1, seed=seed)
    synchronised = track_scene(scene, references=references, clocks=base)
    unsynchronised = track_scene(scene, references=references, clocks=offsets)
    np.testing.assert_array_equal(synchronised.captured_frames, unsynchronised.captured_frames)
    assert hota(scene, unsynchronised) >= hota(scene, synchronised) - 1.0
    assert one_row_per_frame_and_track(unsynchronised.tracks)
    assert set(unsynchronised.tracks.frame.tolist()) == set(scene.frames.tolist())
    assert not any(report["beyond_tolerance"] for report in unsynchronised.clocks.values())


@pytest.mark.parametrize("spread_s", [0.02, 0.05])
def test_plaza_at_10_and_15_fps_with_clock_offsets(plaza, plaza_synchronised_hota, spread_s):
    """Cameras at 10 and 15 fps: capture instants 33 ms apart, clocks off by up to ±50 ms.
    Every captured frame is reported once per track, and HOTA stays within a point."""
    scene, references = plaza
    offsets = ClockSimulation(
        offset_s=spread_s, jitter_s=0.003, camera_fps=(10.0, 15.0), drop=0.1, seed=1
    )
    unsynchronised = track_scene(scene, references=references, clocks=offsets)
    assert hota(scene, unsynchronised) >= plaza_synchronised_hota - 1.0
    assert one_row_per_frame_and_track(unsynchronised.tracks)
    # Frames 1, 5, 7, ... (30 fps) are captured by no camera: they are not reported.
    assert set(unsynchronised.tracks.frame.tolist()) <= set(unsynchronised.captured_frames)
    assert len(set(unsynchronised.tracks.frame.tolist())) >= 0.98 * len(
        unsynchronised.captured_frames
    )


def test_cli_reproduces_a_row_of_the_asynchrony_table(tmp_path, capsys):
    out = tmp_path / "tracks.txt"
    code = main(
        [
            "track",
            "synthetic:plaza",
            "--duration",
            "10",
            "--camera-fps",
            "10,15",
            "--clock-offset-ms",
            "50",
            "--clock-jitter-ms",
            "3",
            "--drop-messages",
            "0.1",
            "--seed",
            "1",
            "--out",
            str(out),
            "--score",
            "--json",
            "--quiet",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cameras"] == 4 and summary["frames"] == 300  # 30 fps for 10 + 15 fps
    assert 150 < summary["captured_frames"] < 200  # 2 of every 3 frames, some lost
    assert summary["scores"]["HOTA"] > 80.0
    assert set(summary["clocks"]) == {"NW", "NE", "SE", "SW"}
    tracks = read_tracks(out)
    assert len(tracks) == summary["rows"] and one_row_per_frame_and_track(tracks)


def test_cli_names_a_camera_with_a_wrong_clock(wildtrack_first_frames, tmp_path, capsys):
    """On WILDTRACK's first 40 frames (20 s): the 2 s error is found as on all 200."""
    code = main(
        [
            "track",
            str(wildtrack_first_frames(40)),
            "--out",
            str(tmp_path / "t.txt"),
            "--clock-error",
            "IDIAP2=-2",
            "--quiet",
        ]
    )
    assert code == 0
    output = capsys.readouterr().out
    assert "camera IDIAP2: clock off by -2.0" in output


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--camera-fps", "10,fast"], "--camera-fps must be comma-separated frame rates"),
        (["--camera-fps", "10,-5"], "--camera-fps must be positive frame rates"),
        (["--camera-fps", "7"], "whole multiple"),
        (["--drop-messages", "1.5"], "--drop-messages must be in [0, 1)"),
        (["--clock-offset-ms", "-3"], "--clock-offset-ms must be >= 0"),
        (["--clock-error", "CVLab1:2"], "a clock error must be CAMERA=SECONDS"),
        (["--clock-error", "north=2"], "clock errors name unknown camera(s) ['north']"),
    ],
)
def test_cli_clock_mistakes(wildtrack_root, tmp_path, capsys, arguments, message):
    code = main(
        ["track", str(wildtrack_root), "--out", str(tmp_path / "t.txt"), "--quiet", *arguments]
    )
    assert code != 0
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["synthetic:garden"], "unknown synthetic preset 'garden'"),
        (["synthetic:plaza", "--duration", "0"], "--duration must be a positive number"),
        (["synthetic:plaza", "--detections", "x"], "a synthetic scene has no images"),
    ],
)
def test_cli_synthetic_mistakes(tmp_path, capsys, arguments, message):
    code = main(["track", *arguments, "--out", str(tmp_path / "t.txt"), "--quiet"])
    assert code != 0
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error
