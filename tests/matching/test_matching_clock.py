"""Camera clock offsets estimated from the data: convergence, wrong clocks.

That synchronised WILDTRACK cameras keep their timestamps is checked in
tests/pipeline/test_pipeline_track.py, on the runs its scoring tests track."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from cblrs.datasets import load_scene
from cblrs.datasets.clocks import ClockSimulation, camera_clocks
from cblrs.datasets.presets import make_scene
from cblrs.evaluation import evaluate
from cblrs.matching import make_matcher
from cblrs.matching.clock import ClockModel
from cblrs.pipeline import (
    camera_messages,
    camera_positions,
    ordered_windows,
    render_scene_references,
    scene_planes,
    track_scene,
)


@pytest.fixture(scope="module")
def plaza():
    scene = make_scene("plaza", fps=10.0, duration_s=20.0)
    return scene, render_scene_references(scene)


@pytest.fixture(scope="module")
def wildtrack(wildtrack_root):
    scene = load_scene(wildtrack_root)
    return scene, render_scene_references(scene)


def relative_error_ms(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Estimated minus true offsets, each relative to its median camera, milliseconds."""
    return ((estimated - np.median(estimated)) - (truth - np.median(truth))) * 1000


def test_estimated_offsets_converge_to_the_true_ones(plaza):
    """Four cameras off by up to ±50 ms, jittered by 3 ms, 10 % of messages lost: the
    estimate starts at zero and ends within 3 ms of the truth."""
    scene, references = plaza
    clocks = ClockSimulation(offset_s=0.05, jitter_s=0.003, drop=0.1, seed=3)
    truth = np.array([clock.offset_s for clock in camera_clocks(scene, clocks)])
    matcher = make_matcher(
        "fusion", scene_planes(scene), scene.camera_names, camera_positions=camera_positions(scene)
    )
    errors = []
    for timestamp, window in ordered_windows(
        camera_messages(scene, references, None, clocks), scene.camera_names
    ):
        matcher.update(timestamp, window)
        errors.append((timestamp, np.abs(relative_error_ms(matcher._clock.offsets, truth)).max()))
    early = max(error for timestamp, error in errors if timestamp < 3.0)
    late = max(error for timestamp, error in errors if timestamp > 16.0)
    assert early > 20.0  # the true offsets are tens of milliseconds: the start is wrong
    assert late < 3.0
    report = matcher.clock_report()
    assert set(report) == set(scene.camera_names)
    assert all(one["uncertainty_s"] < 0.005 for one in report.values())
    assert not any(one["beyond_tolerance"] for one in report.values())  # all within 0.2 s


def test_a_wrong_clock_is_found_reported_and_corrected_on_synthetic_data(plaza, caplog):
    scene, references = plaza
    clocks = ClockSimulation(
        offset_s=0.02, jitter_s=0.003, drop=0.1, seed=1, clock_errors={"NE": 2.0}
    )
    with caplog.at_level(logging.WARNING, logger="cblrs.matching.fusion"):
        corrected = track_scene(scene, references=references, clocks=clocks)
    report = corrected.clocks["NE"]
    truth = {clock.camera: clock.offset_s for clock in camera_clocks(scene, clocks)}
    assert report["beyond_tolerance"] and report["coarse_corrections"] == 1
    assert report["offset_s"] == pytest.approx(
        truth["NE"] - np.median(list(truth.values())), abs=0.03
    )
    assert "camera NE: clock off by +2.0" in caplog.text
    trusting = track_scene(scene, references=references, clocks=clocks, estimate_clocks=False)
    frames = corrected.captured_frames
    hota = evaluate(scene.ground_truth, corrected.tracks, frames=frames).HOTA
    assert hota > 80.0  # 91 synchronised; the first seconds cost until the clock is found
    # Trusting the wrong clock costs less since multi-view confirmation (the wrong camera's
    # views, seen by it alone, no longer confirm ghost tracks), but still costs.
    assert hota > evaluate(scene.ground_truth, trusting.tracks, frames=frames).HOTA + 3.0


@pytest.mark.parametrize("error_s", [2.0, -2.0])
def test_a_camera_two_seconds_off_is_found_on_wildtrack(wildtrack, error_s):
    """CVLab4 sees few people and many of them stand: its clock is found all the same."""
    scene, references = wildtrack
    clocks = ClockSimulation(
        offset_s=0.02, jitter_s=0.003, drop=0.1, seed=1, clock_errors={"CVLab4": error_s}
    )
    corrected = track_scene(scene, references=references, clocks=clocks)
    report = corrected.clocks["CVLab4"]
    assert report["beyond_tolerance"] and report["coarse_corrections"] == 1
    assert report["offset_s"] == pytest.approx(error_s, abs=0.06)
    others = [one for name, one in corrected.clocks.items() if name != "CVLab4"]
    assert not any(one["beyond_tolerance"] or one["coarse_corrections"] for one in others)
    trusting = track_scene(scene, references=references, clocks=clocks, estimate_clocks=False)
    frames = corrected.captured_frames
    hota = evaluate(scene.ground_truth, corrected.tracks, frames=frames).HOTA
    assert hota > 85.0
    assert hota > evaluate(scene.ground_truth, trusting.tracks, frames=frames).HOTA + 5.0


def test_a_bias_that_follows_the_flow_is_not_taken_for_a_clock():
    """In each place everyone walks one way and a camera sees them 10 cm further on (a
    calibration error): a pooled fit would call that a clock 75 ms ahead. Fitted within each
    ground cell, the offset stays near zero; a true 40 ms offset is still found."""
    rng = np.random.default_rng(0)
    for true_offset, expected in ((0.0, 0.0), (0.04, 0.04)):
        model = ClockModel(2, max_offset_s=0.0)
        model.apply_corrections = False
        for _ in range(300):
            cells = rng.integers(0, 20, 20)
            position = np.column_stack([cells * 2.0 + 1.0, rng.uniform(0, 2, 20)])
            direction = np.where(cells % 2 == 0, 1.0, -1.0)
            speed = rng.uniform(0.8, 1.6, 20)
            velocity = np.column_stack([np.zeros(20), direction * speed])
            bias = np.column_stack([np.zeros(20), 0.1 * direction])
            noise = rng.normal(0, 0.02, (2, 20, 2))
            camera_0 = position + noise[0]
            camera_1 = position + bias - velocity * true_offset + noise[1]
            model.learn(
                np.repeat([0, 1], 20),
                np.tile(np.arange(20), 2),
                np.concatenate([camera_0, camera_1]),
                np.tile(0.02**2 * np.eye(2), (40, 1, 1)),
                np.concatenate([velocity, velocity]),
            )
        model.end_window(0.0)
        step = model.solve()
        assert step is not None
        assert step[1] - step[0] == pytest.approx(expected, abs=0.01)


def test_the_coarse_search_finds_a_lag_of_seconds():
    rng = np.random.default_rng(1)
    model = ClockModel(2, max_offset_s=5.0)
    start = rng.uniform(0, 30, (30, 2))
    velocity = rng.normal(0, 1.0, (30, 2))
    for step in range(200):
        time_s = step * 0.1
        truth = start + velocity * time_s
        # Camera 1's clock is 1.5 s ahead: what it saw at time t it stamps t + 1.5.
        model.record(
            time_s,
            truth,
            np.zeros(30, np.int64),
            np.ones(30, np.int64),
            truth,
            np.full(30, time_s + 1.5),
        )
    found = model._best_lag(1)
    assert found is not None
    lag, gain = found
    assert lag == pytest.approx(1.5, abs=0.06) and gain > 2.0


def test_clock_model_state_round_trip():
    rng = np.random.default_rng(2)
    model = ClockModel(3)
    for step in range(50):
        velocity = rng.normal(0, 1, (10, 2))
        positions = rng.uniform(0, 10, (10, 2))
        model.learn(
            np.repeat([0, 1], 5),
            np.tile(np.arange(5), 2),
            positions,
            np.tile(0.01 * np.eye(2), (10, 1, 1)),
            velocity,
        )
        model.record(
            step * 0.1,
            positions,
            np.full(10, -1),
            np.repeat([0, 1], 5),
            positions,
            np.full(10, step * 0.1),
        )
        model.end_window(step * 0.1)
    copy = ClockModel(3)
    copy.set_state(json.loads(json.dumps(model.get_state())))
    assert copy.report(["a", "b", "c"]) == model.report(["a", "b", "c"])
    np.testing.assert_array_equal(copy.solve(), model.solve())
