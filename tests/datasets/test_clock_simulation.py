"""Simulated camera clocks: offsets, jitter, frame rates, lost messages; seeded."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.datasets.clocks import ClockSimulation, camera_clocks, parse_clock_errors
from cblrs.datasets.presets import make_scene
from cblrs.errors import DatasetError


@pytest.fixture(scope="module")
def scene():
    return make_scene("plaza", fps=30.0, duration_s=20.0)


def test_offsets_jitter_and_losses(scene):
    simulation = ClockSimulation(offset_s=0.05, jitter_s=0.003, drop=0.1, seed=4)
    clocks = camera_clocks(scene, simulation)
    assert [clock.camera for clock in clocks] == scene.camera_names
    for clock in clocks:
        assert abs(clock.offset_s) <= 0.05
        error = clock.timestamp - scene.timestamps[clock.frame_index] - clock.offset_s
        assert abs(error.mean()) < 0.001 and 0.002 < error.std() < 0.004
        assert np.all(np.diff(clock.timestamp) > 0)  # a clock never runs backwards
        assert 0.85 < len(clock.frame_index) / len(scene.frames) < 0.95
    assert len({round(clock.offset_s, 9) for clock in clocks}) == len(clocks)


def test_frame_rates_keep_every_kth_frame(scene):
    clocks = camera_clocks(scene, ClockSimulation(camera_fps=(10.0, 15.0)))
    steps = [np.unique(np.diff(clock.frame_index)).tolist() for clock in clocks]
    assert steps == [[3], [2], [3], [2]]  # cycled over the four cameras
    assert ClockSimulation(camera_fps=(10.0, 15.0)).scene_fps(5.0) == 30.0
    assert ClockSimulation(camera_fps=(2.5, 10.0)).scene_fps(5.0) == 10.0
    assert ClockSimulation().scene_fps(5.0) == 5.0


def test_same_seed_same_clocks_and_streams_are_independent(scene):
    first = camera_clocks(scene, ClockSimulation(offset_s=0.02, drop=0.1, seed=7))
    again = camera_clocks(scene, ClockSimulation(offset_s=0.02, drop=0.1, seed=7))
    other_offsets = camera_clocks(scene, ClockSimulation(offset_s=0.05, drop=0.1, seed=7))
    for one, two, three in zip(first, again, other_offsets, strict=True):
        np.testing.assert_array_equal(one.timestamp, two.timestamp)
        # A wider spread changes the offsets, not which messages are lost.
        np.testing.assert_array_equal(one.frame_index, three.frame_index)


def test_a_wrong_clock_and_the_synchronised_case(scene):
    clocks = camera_clocks(scene, ClockSimulation(clock_errors={"SE": -2.0}))
    assert [clock.offset_s for clock in clocks] == [0.0, 0.0, -2.0, 0.0]
    assert ClockSimulation().synchronised
    assert not ClockSimulation(drop=0.1).synchronised
    assert parse_clock_errors(["SE=-2", "NW=0.5"]) == {"SE": -2.0, "NW": 0.5}


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"offset_s": -1.0}, "offset_s must be a finite number >= 0"),
        ({"jitter_s": float("nan")}, "jitter_s must be a finite number >= 0"),
        ({"drop": 1.0}, "drop must be in [0, 1)"),
        ({"camera_fps": (10.0, 0.0)}, "camera frame rates must be positive"),
        ({"clock_errors": {"SE": float("inf")}}, "clock errors must be finite seconds"),
        ({"seed": -1}, "seed must be a non-negative integer"),
    ],
)
def test_bad_simulations(options, message):
    with pytest.raises(DatasetError, match=message.replace("[", r"\[").replace(")", r"\)")
                       .replace("(", r"\(")):
        ClockSimulation(**options)


def test_bad_schedules(scene):
    with pytest.raises(DatasetError, match="whole multiple"):
        camera_clocks(scene, ClockSimulation(camera_fps=(7.0,)))
    with pytest.raises(DatasetError, match="unknown camera"):
        camera_clocks(scene, ClockSimulation(clock_errors={"north": 1.0}))
    with pytest.raises(DatasetError, match="CAMERA=SECONDS"):
        parse_clock_errors(["SE:2"])
