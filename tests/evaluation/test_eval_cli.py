"""``cblrs eval`` end to end, and the shared --frames parser."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cblrs.cli.common import UsageError, parse_frame_range
from cblrs.cli.main import main
from cblrs.datasets.aicity import write_tracks
from cblrs.detections import Tracks

KEYS = ["HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1"]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0:995", (0, 995)),
        ("100:", (100, None)),
        (":995", (None, 995)),
        (":", (None, None)),
        (" 5 : 5 ", (5, 5)),
    ],
)
def test_parse_frame_range(text: str, expected: tuple) -> None:
    assert parse_frame_range(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("100", "must be FIRST:LAST"),
        ("1:2:3", "must be FIRST:LAST"),
        ("", "must be FIRST:LAST"),
        ("a:5", "'a' is not a non-negative integer"),
        ("-5:10", "'-5' is not a non-negative integer"),
        ("1.5:3", "'1.5' is not a non-negative integer"),
        ("10:5", "is empty: FIRST 10 is after LAST 5"),
    ],
)
def test_parse_frame_range_errors(text: str, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        parse_frame_range(text)


def switch_example(folder: Path) -> tuple[Path, Path]:
    """Two objects over frames 0..9; object 0 switches id at frame 5 (AssA 75, IDF1 75)."""
    frame = np.repeat(np.arange(10), 2)
    track_id = np.tile([0, 1], 10)
    world_xy = np.stack([0.25 * frame, 10.0 * track_id], axis=1)
    truth = Tracks(frame, frame / 2.0, track_id, world_xy)
    predicted_id = np.where(track_id == 1, 2, np.where(frame < 5, 1, 3))
    predictions = Tracks(frame, frame / 2.0, predicted_id, world_xy, camera_id=np.zeros(20))
    truth_path, tracks_path = folder / "gt.txt", folder / "tracks.txt"
    write_tracks(truth_path, truth)
    write_tracks(tracks_path, predictions)
    return truth_path, tracks_path


def test_eval_json_has_exactly_the_six_keys(tmp_path: Path, capsys) -> None:
    truth, tracks = switch_example(tmp_path)
    assert main(["eval", str(truth), str(tracks), "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert list(scores) == KEYS
    assert scores["AssA"] == pytest.approx(75.0)
    assert scores["IDF1"] == pytest.approx(75.0)
    assert scores["MOTA"] == pytest.approx(95.0)


def test_eval_frames_option(tmp_path: Path, capsys) -> None:
    truth, tracks = switch_example(tmp_path)
    assert main(["eval", str(truth), str(tracks), "--json", "--frames", ":4"]) == 0
    assert json.loads(capsys.readouterr().out) == {key: 100.0 for key in KEYS}


def test_eval_table(tmp_path: Path, capsys) -> None:
    truth, tracks = switch_example(tmp_path)
    assert main(["eval", str(truth), str(tracks)]) == 0
    output = capsys.readouterr().out
    assert output.split()[:6] == KEYS
    assert "75.000" in output and "1 id switches" in output


@pytest.mark.parametrize(
    ("arguments", "code", "message"),
    [
        (["--frames", "9:3"], 2, "frame range '9:3' is empty"),
        (["--frames", "x:"], 2, "'x' is not a non-negative integer"),
        (["--frames", "50:"], 2, "--frames 50: holds no ground-truth frame"),
    ],
)
def test_eval_usage_errors(tmp_path: Path, capsys, arguments, code, message) -> None:
    truth, tracks = switch_example(tmp_path)
    assert main(["eval", str(truth), str(tracks), *arguments]) == code
    assert message in capsys.readouterr().err


def test_eval_missing_inputs(tmp_path: Path, capsys) -> None:
    truth, tracks = switch_example(tmp_path)
    assert main(["eval", str(tmp_path / "nowhere"), str(tracks)]) == 1
    assert "neither a dataset folder nor a ground-truth file" in capsys.readouterr().err
    assert main(["eval", str(truth), str(tmp_path / "missing.txt")]) == 1
    assert "tracks file" in capsys.readouterr().err
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    assert main(["eval", str(truth), str(tmp_path / "bad.txt")]) == 1
    assert "bad.txt:1: expected 9 columns" in capsys.readouterr().err


def test_eval_on_wildtrack(wildtrack_root: Path, tmp_path: Path, capsys) -> None:
    from cblrs.datasets import load_scene

    truth = load_scene(wildtrack_root).ground_truth
    # Keep only the first 20 frames in the predictions; evaluate over frames 0..95 only.
    tracks = tmp_path / "tracks.txt"
    write_tracks(tracks, truth[truth.frame < 100])
    assert main(["eval", str(wildtrack_root), str(tracks), "--json", "--frames", ":95"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores == pytest.approx({key: 100.0 for key in KEYS})
    assert main(["eval", str(wildtrack_root), str(tracks), "--json"]) == 0
    recall_limited = json.loads(capsys.readouterr().out)
    assert recall_limited["MOTA"] == pytest.approx(100.0 * (truth.frame < 100).sum() / len(truth))


def _wildtrack_variants(root: Path, folder: Path) -> dict[str, Path]:
    """Ground truth of WILDTRACK written back as predictions, and four ways to get it wrong."""
    from cblrs.datasets import load_scene

    truth = load_scene(root).ground_truth
    frames = np.unique(truth.frame)
    variants = {
        "right": truth,
        "empty": Tracks.empty(),
        "half the frames": truth[truth.frame <= np.median(frames)],
        "frame indices": Tracks(np.searchsorted(frames, truth.frame), truth.timestamp,
                                truth.track_id, truth.world_xy),
        "centimetres": Tracks(truth.frame, truth.timestamp, truth.track_id,
                              100.0 * truth.world_xy),
    }
    paths = {}
    for name, tracks in variants.items():
        paths[name] = folder / f"{name.replace(' ', '_')}.txt"
        write_tracks(paths[name], tracks)
    return paths


@pytest.mark.parametrize(
    ("variant", "warning"),
    [
        ("right", None),
        ("empty", "has no rows"),
        ("half the frames", r"rows in 100 of the 200 ground-truth frames \(50 %"),
        ("frame indices", r"look like indices of the 200 ground-truth frames, not their native "
                          r"numbers \(0\.\.995 \(every 5th\)\)"),
        ("centimetres", r"spread 100 times as far .*\(centimetres instead of metres\?\)"),
    ],
)
def test_eval_warns_about_a_predictions_file_that_looks_wrong(
    wildtrack_root, tmp_path, capsys, variant, warning
):
    import re

    paths = _wildtrack_variants(wildtrack_root, tmp_path)
    assert main(["eval", str(wildtrack_root), str(paths[variant]), "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)  # still scored
    warnings = [line for line in captured.err.splitlines() if "warning:" in line]
    if warning is None:
        assert warnings == []
    else:
        assert len(warnings) == 1 and re.search(warning, warnings[0]), captured.err
