"""The in-process pipeline and `cblrs track`: synthetic scenes and WILDTRACK.

WILDTRACK's runs (all frames, about a CPU-second each) are tracked once per module and shared
by the tests that score them and the test that checks the clock estimate leaves synchronised
cameras alone (it was in tests/matching/test_matching_clock.py and tracked the same inputs
again); no test changes a result it is given."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks, simulate_detections
from cblrs.datasets.presets import make_scene
from cblrs.evaluation import evaluate
from cblrs.pipeline import render_scene_references, scene_messages, track_scene


@pytest.fixture(scope="module")
def roundabout():
    return make_scene("roundabout")


@pytest.fixture(scope="module")
def wildtrack(wildtrack_root):
    scene = load_scene(wildtrack_root)
    return scene, render_scene_references(scene)


@pytest.fixture(scope="module")
def wildtrack_runs(wildtrack):
    """``run(seed, estimate_clocks=True)``: (scene, TrackResult) of WILDTRACK with exact boxes
    (seed None) or the noisy detector's (20 % dropped, 5 % jitter, that seed), each tracked
    once in this module."""
    scene, references = wildtrack
    scenes: dict = {}
    results: dict = {}

    def run(seed, estimate_clocks=True):
        if seed not in scenes:
            scenes[seed] = scene if seed is None else simulate_detections(
                scene, drop=0.2, jitter=0.05, seed=seed)
        key = (seed, estimate_clocks)
        if key not in results:
            options = {} if estimate_clocks else {"estimate_clocks": False}
            results[key] = track_scene(scenes[seed], references=references, **options)
        return scenes[seed], results[key]

    return run


def test_messages_carry_colours_for_every_camera_and_frame(roundabout):
    references = render_scene_references(roundabout, bits=8)
    instants = list(scene_messages(roundabout, references))
    assert len(instants) == len(roundabout.frames)
    timestamp, messages = instants[3]
    assert timestamp == pytest.approx(roundabout.timestamps[3])
    assert [message.camera_id for message in messages] == ["A", "B"]
    assert all(message.frame == roundabout.frames[3] for message in messages)
    assert all(message.colour.shape == (len(message), 3) for message in messages)


def test_roundabout_car_keeps_one_identity_through_both_hand_overs(roundabout):
    result = track_scene(roundabout)
    assert set(result.tracks.track_id.tolist()) == {1}
    assert set(result.tracks.frame.tolist()) <= set(roundabout.frames.tolist())
    # Reported from both cameras at some point: the identity was handed over.
    assert set(result.tracks.camera_id.tolist()) == {0, 1}
    assert result.message_count == 2 * len(roundabout.frames)
    assert result.matcher_seconds <= result.total_seconds


@pytest.mark.parametrize("matcher", ["fusion", "paper"])
def test_plaza_through_both_matchers(matcher):
    scene = make_scene("plaza", duration_s=8.0)
    result = track_scene(scene, matcher, bits=8)
    metrics = evaluate(scene.ground_truth, result.tracks)
    assert len(result.references) == len(scene.cameras)
    assert metrics.DetA > 50.0  # both localise people through the colour path
    assert result.detection_count == sum(
        len(boxes) for per_camera in scene.detections for boxes in per_camera)


def test_track_scene_rejects_options_with_an_instance(roundabout):
    from cblrs.matching import make_matcher
    from cblrs.pipeline import scene_planes

    matcher = make_matcher("paper", scene_planes(roundabout), roundabout.camera_names)
    with pytest.raises(ValueError, match="only accepted with a matcher name"):
        track_scene(roundabout, matcher, threshold_m=2.0)


def test_wildtrack_fusion_scores(wildtrack_runs):
    """Exact annotated boxes, all frames, through the colour path.

    The benchmark target is HOTA >= 92 and IDF1 >= 95 over all frames; the tracker reaches
    HOTA 93.76 and IDF1 95.59 (frames 100..995: 95.1 / 97.1; the first 20 annotated frames
    hold most of the implausible ground-truth jumps). The pipeline is deterministic; these
    guard against regressions with a small margin below the measured figures.
    """
    scene, result = wildtrack_runs(None)
    metrics = evaluate(scene.ground_truth, result.tracks)
    assert metrics.HOTA >= 93.5
    assert metrics.IDF1 >= 95.2
    late = evaluate(scene.ground_truth, result.tracks, frames=scene.frames[scene.frames >= 100])
    assert late.HOTA >= 95.0
    assert late.IDF1 >= 96.5


@pytest.mark.parametrize(("seed", "measured"), [(0, 86.08), (1, 86.72), (2, 84.88)])
def test_wildtrack_fusion_with_a_noisy_detector(wildtrack_runs, seed, measured):
    """20 % of boxes dropped and every edge jittered by 5 % of the box size.

    The target is HOTA >= 85. Seeds 0..6 measure 86.08, 86.72, 84.88, 87.08, 86.02, 86.48,
    86.16 (mean 86.20; IDF1 mean 92.6); seed 2 is the lowest of them. The oracle with
    ground-truth identities and the same filter reaches about 93.5. Each seed is guarded
    half a point below its measured figure (the pipeline is deterministic).
    """
    scene, _ = wildtrack_runs(None)
    _, result = wildtrack_runs(seed)
    metrics = evaluate(scene.ground_truth, result.tracks)
    assert metrics.HOTA >= measured - 0.5
    assert metrics.IDF1 >= 90.0


@pytest.mark.parametrize("seed", [None, 2])
def test_synchronised_cameras_keep_their_timestamps(wildtrack_runs, seed):
    """On WILDTRACK (exact boxes, and a noisy detector) no offset is significant: the tracks
    are exactly those of a tracker that trusts the timestamps."""
    _, estimating = wildtrack_runs(seed)
    _, trusting = wildtrack_runs(seed, estimate_clocks=False)
    assert all(one["offset_s"] == 0.0 for one in estimating.clocks.values())
    np.testing.assert_array_equal(estimating.tracks.world_xy, trusting.tracks.world_xy)
    np.testing.assert_array_equal(estimating.tracks.track_id, trusting.tracks.track_id)


def test_cli_track_writes_valid_tracks(wildtrack_root, tmp_path, capsys):
    out = tmp_path / "tracks.txt"
    code = main(["track", str(wildtrack_root), "--out", str(out), "--frames", "0:100",
                 "--quiet"])
    assert code == 0
    tracks = read_tracks(out)
    assert set(tracks.frame.tolist()) <= set(range(0, 101, 5))
    assert len(tracks) > 100 and np.isfinite(tracks.world_xy).all()
    assert "fusion: 21 frames x 7 cameras" in capsys.readouterr().out


def test_cli_track_with_a_noisy_detector_and_json(wildtrack_root, tmp_path, capsys):
    out = tmp_path / "noisy.txt"
    code = main(["track", str(wildtrack_root), "--out", str(out), "--frames", "0:50",
                 "--drop", "0.2", "--jitter", "0.05", "--false-positives", "1", "--seed", "3",
                 "--matcher", "paper", "--bits", "8", "--json", "--quiet"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["matcher"] == "paper" and summary["frames"] == 11
    assert summary["rows"] == len(read_tracks(out))


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--drop", "1.5"], "--drop is a probability and must be at most 1"),
        (["--jitter", "-0.1"], "--jitter must be >= 0"),
        (["--frames", "9000:9100"], "no frames in 9000:9100"),
        (["--frames", "50"], "must be FIRST:LAST"),
    ],
)
def test_cli_track_errors(wildtrack_root, tmp_path, capsys, arguments, message):
    code = main(["track", str(wildtrack_root), "--out", str(tmp_path / "t.txt"), *arguments])
    assert code != 0
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error
