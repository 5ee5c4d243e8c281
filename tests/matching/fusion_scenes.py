"""Shared scenes for the fusion tracker tests: three cameras around a plaza, walkers on circles."""

from __future__ import annotations

import numpy as np

from cblrs.detections import CameraMessage, Tracks
from cblrs.plane import PlaneSet, PlaneSpec

PLANES = PlaneSet([PlaneSpec(1, (-10.0, -10.0), 40.0, 40.0)])


CAMERAS = ["north", "east", "south"]


CAMERA_XY = {"north": (5.0, 22.0), "east": (22.0, 5.0), "south": (5.0, -12.0)}


def walkers(times: np.ndarray) -> np.ndarray:
    """(F, 3, 2) positions of three people walking straight lines, 2 m apart or more."""
    start = np.array([[0.0, 0.0], [4.0, 6.0], [10.0, 2.0]])
    velocity = np.array([[1.2, 0.3], [-0.8, 0.9], [0.2, -1.1]])
    return start[None] + times[:, None, None] * velocity[None]


def camera_message(camera: str, frame: int, timestamp: float, points: np.ndarray,
                   rng: np.random.Generator, noise_m: float = 0.05) -> CameraMessage:
    noisy = points + rng.normal(0.0, noise_m, size=points.shape)
    colour, valid = PLANES[0].encode(noisy.reshape(-1, 2))
    assert valid.all()
    count = len(colour)
    boxes = np.column_stack([np.arange(count) * 50.0, np.zeros(count),
                             np.arange(count) * 50.0 + 30.0, np.full(count, 80.0 + frame)])
    return CameraMessage(camera, frame, timestamp, frame, boxes, np.ones(count),
                         np.zeros(count, np.int64), colour.astype(np.int64))


def sequence(fps: float = 2.0, seconds: float = 10.0, seed: int = 0, offsets=(0.0, 0.0, 0.0),
             missing: dict | None = None):
    """Per frame: list of (timestamp, [messages]) instants; cameras may be offset in time."""
    rng = np.random.default_rng(seed)
    frames = np.arange(int(seconds * fps))
    instants = []
    for frame in frames:
        per_time: dict[float, list[CameraMessage]] = {}
        for camera, offset in zip(CAMERAS, offsets, strict=True):
            timestamp = frame / fps + offset
            points = walkers(np.array([timestamp]))[0]
            keep = [index for index in range(3)
                    if (missing or {}).get((int(frame), index)) is None]
            per_time.setdefault(timestamp, []).append(
                camera_message(camera, int(frame), timestamp, points[keep], rng))
        instants.extend(sorted(per_time.items()))
    return instants


def run(tracker, instants, flush: bool = True) -> Tracks:
    """Feed instants; with ``flush`` the stream ends there (the tracker fuses all it holds)."""
    parts = [tracker.update(timestamp, messages) for timestamp, messages in instants]
    if flush:
        parts.append(tracker.flush())
    return Tracks.concatenate(parts)


def identities(tracks: Tracks, times: np.ndarray) -> dict[int, set[int]]:
    """For each true walker, the set of track ids reported on it."""
    truth = walkers(tracks.timestamp)
    nearest = np.argmin(np.linalg.norm(truth - tracks.world_xy[:, None], axis=2), axis=1)
    return {walker: set(tracks.track_id[nearest == walker].tolist()) for walker in range(3)}

