"""simulate_detections: seeded drop, jitter and false positives over ground-truth boxes."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets import Scene
from cblrs.datasets.simulate import simulate_detections
from cblrs.detections import Detections, Tracks
from cblrs.errors import DatasetError
from cblrs.plane import PlaneSpec

IMAGE_SIZE = (640, 480)


def make_scene(frames: int = 50, boxes_per_frame: tuple[int, ...] = (20, 0)) -> Scene:
    """Cameras with fixed per-frame boxes (camera 1 may have none); one GT object per box."""
    cameras = [
        Camera.from_pose(f"cam{index}", (0.0, -10.0, 5.0), 0.0, 30.0, 500.0, IMAGE_SIZE)
        for index in range(len(boxes_per_frame))
    ]
    random = np.random.default_rng(123)
    detections = []
    for _ in range(frames):
        per_camera = []
        for count in boxes_per_frame:
            corner = random.uniform(0, 300, (count, 2))
            size = random.uniform(20, 120, (count, 2))
            per_camera.append(
                Detections(
                    xyxy=np.concatenate([corner, corner + size], axis=1),
                    confidence=np.ones(count),
                    class_id=np.zeros(count, np.int64),
                    object_id=np.arange(count),
                )
            )
        detections.append(per_camera)
    frame = np.arange(frames)
    truth = Tracks(np.repeat(frame, 2), np.repeat(frame / 2.0, 2), np.tile([0, 1], frames),
                   np.zeros((2 * frames, 2)))
    return Scene("test", cameras, frame, frame / 2.0, detections, truth,
                 PlaneSpec(1, (0.0, 0.0), 10.0, 10.0))


def all_boxes(scene: Scene, camera: int = 0) -> Detections:
    return Detections.concatenate([frame[camera] for frame in scene.detections])


def test_all_off_returns_the_same_scene() -> None:
    scene = make_scene()
    assert simulate_detections(scene) is scene
    assert simulate_detections(scene, seed=5) is scene


@pytest.mark.parametrize(("drop", "expected_kept"), [(0.0, 1000), (1.0, 0)])
def test_drop_extremes(drop: float, expected_kept: int) -> None:
    scene = make_scene()
    noisy = simulate_detections(scene, drop=drop, jitter=0.0 if drop else 0.01)
    assert len(all_boxes(noisy)) == expected_kept
    assert noisy.ground_truth is scene.ground_truth
    np.testing.assert_array_equal(noisy.frames, scene.frames)


def test_drop_rate_and_kept_boxes_unchanged() -> None:
    scene = make_scene()
    noisy = simulate_detections(scene, drop=0.3, seed=1)
    kept = len(all_boxes(noisy))
    # Binomial(1000, 0.7): mean 700, sigma 14.5; 5 sigma bounds.
    assert 627 < kept < 773
    for original, degraded in zip(scene.detections, noisy.detections, strict=True):
        survivors = np.isin(original[0].object_id, degraded[0].object_id)
        np.testing.assert_array_equal(original[0].xyxy[survivors], degraded[0].xyxy)


def test_jitter_is_relative_to_box_size() -> None:
    scene = make_scene()
    noisy = simulate_detections(scene, jitter=0.1, seed=2)
    before, after = all_boxes(scene), all_boxes(noisy)
    np.testing.assert_array_equal(before.object_id, after.object_id)
    width = before.xyxy[:, 2] - before.xyxy[:, 0]
    height = before.xyxy[:, 3] - before.xyxy[:, 1]
    relative = (after.xyxy - before.xyxy) / np.stack([width, height, width, height], axis=1)
    # 4000 normal samples of sigma 0.1: the sample sigma is within a few percent.
    assert np.std(relative) == pytest.approx(0.1, rel=0.05)
    assert abs(np.mean(relative)) < 0.01
    assert np.all(after.xyxy[:, 2] >= after.xyxy[:, 0])
    assert np.all(after.xyxy[:, 3] >= after.xyxy[:, 1])


def test_huge_jitter_keeps_boxes_ordered() -> None:
    after = all_boxes(simulate_detections(make_scene(), jitter=5.0))
    assert np.all(after.xyxy[:, 2] >= after.xyxy[:, 0])
    assert np.all(after.xyxy[:, 3] >= after.xyxy[:, 1])


def test_false_positives() -> None:
    scene = make_scene()
    noisy = simulate_detections(scene, false_positives=2.0, seed=3)
    for camera in (0, 1):
        boxes = all_boxes(noisy, camera)
        spurious = boxes[boxes.object_id == -1]
        # Poisson(2) over 50 frames: mean 100, sigma 10.
        assert 50 < len(spurious) < 150
        width, height = IMAGE_SIZE
        assert np.all(spurious.xyxy[:, :2] >= 0)
        assert np.all(spurious.xyxy[:, 2] <= width - 1)
        assert np.all(spurious.xyxy[:, 3] <= height - 1)
        # Sizes come from the real boxes (20..120 px), also for camera 1, which has none.
        sizes = spurious.xyxy[:, 2:] - spurious.xyxy[:, :2]
        assert sizes.min() >= 20 - 1e-9 and sizes.max() <= 120 + 1e-9
        np.testing.assert_array_equal(spurious.confidence, 1.0)
        np.testing.assert_array_equal(spurious.class_id, 0)
    # The real boxes are untouched.
    real = all_boxes(noisy, 0)
    np.testing.assert_array_equal(real[real.object_id >= 0].xyxy, all_boxes(scene, 0).xyxy)


def test_false_positives_in_a_scene_without_boxes() -> None:
    scene = make_scene(frames=20, boxes_per_frame=(0,))
    boxes = all_boxes(simulate_detections(scene, false_positives=1.0))
    assert len(boxes) > 0
    np.testing.assert_allclose(boxes.xyxy[:, 3] - boxes.xyxy[:, 1], 0.2 * IMAGE_SIZE[1])


def test_seeded_and_streams_independent() -> None:
    scene = make_scene()
    first = simulate_detections(scene, drop=0.2, jitter=0.05, false_positives=0.5, seed=7)
    again = simulate_detections(scene, drop=0.2, jitter=0.05, false_positives=0.5, seed=7)
    other = simulate_detections(scene, drop=0.2, jitter=0.05, false_positives=0.5, seed=8)
    np.testing.assert_array_equal(all_boxes(first).xyxy, all_boxes(again).xyxy)
    assert len(all_boxes(first)) != len(all_boxes(other)) or not np.array_equal(
        all_boxes(first).xyxy, all_boxes(other).xyxy
    )
    # The same boxes are dropped whatever the jitter.
    dropped_only = simulate_detections(scene, drop=0.2, seed=7)
    real = all_boxes(first)[all_boxes(first).object_id >= 0]
    np.testing.assert_array_equal(all_boxes(dropped_only).object_id, real.object_id)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"drop": -0.1}, r"drop must be in \[0, 1\], got -0.1"),
        ({"drop": 1.5}, r"drop must be in \[0, 1\], got 1.5"),
        ({"drop": float("nan")}, r"drop must be in \[0, 1\], got nan"),
        ({"jitter": -1.0}, "jitter must be >= 0, got -1.0"),
        ({"jitter": float("inf")}, "jitter must be >= 0, got inf"),
        ({"false_positives": -2}, "false_positives must be >= 0, got -2"),
        ({"false_positives": "many"}, "false_positives must be a number, got 'many'"),
        ({"seed": -1}, "seed must be a non-negative integer, got -1"),
        ({"seed": 1.5}, "seed must be a non-negative integer, got 1.5"),
    ],
)
def test_invalid_arguments(arguments: dict, message: str) -> None:
    with pytest.raises(DatasetError, match=message):
        simulate_detections(make_scene(frames=2), **arguments)


def test_wildtrack_drop(wildtrack_root) -> None:
    from cblrs.datasets import load_scene

    scene = load_scene(wildtrack_root)
    total = sum(len(detections) for frame in scene.detections for detections in frame)
    noisy = simulate_detections(scene, drop=0.2, jitter=0.05, seed=0)
    kept = sum(len(detections) for frame in noisy.detections for detections in frame)
    sigma = np.sqrt(total * 0.2 * 0.8)
    assert abs(kept - 0.8 * total) < 5 * sigma
