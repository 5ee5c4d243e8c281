"""The synthetic load of ``cblrs bench tracker``, and the oracle tracks of docs/wildtrack.md.

The synthetic load is what the central node sees in steady state: ``live_tracks`` people
walking (constant velocity, bouncing off the borders of an area sized for a realistic
crowd density) seen by ``cameras`` cameras, each detecting each person with probability
0.9 and a ground error of 0.1 m, messages carrying colours of a 16-bit plane. Generating the
messages is excluded from the timing; only ``matcher.update`` is timed
(:func:`measure_throughput`). :func:`oracle_tracks` tracks a scene with the true associations
given (what a perfect association would reach under the same filter and noise).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import numpy as np

from cblrs.detections import CameraMessage, Tracks
from cblrs.edge import make_message
from cblrs.matching import kalman, make_matcher
from cblrs.matching.fusion import fuse, ray_covariance
from cblrs.plane import PlaneSet, PlaneSpec

SQUARE_METRES_PER_PERSON = 10.0
DETECTION_PROBABILITY = 0.9
NOISE_M = 0.1
WALKING_SPEED = 1.3  # m/s


@dataclass(frozen=True)
class SyntheticLoad:
    """Pre-built messages for a throughput run."""

    planes: PlaneSet
    camera_ids: list[str]
    instants: list[tuple[float, list[CameraMessage]]]

    @property
    def detection_count(self) -> int:
        return sum(len(message) for _, messages in self.instants for message in messages)


def synthetic_load(
    live_tracks: int, cameras: int, frames: int, seed: int = 0, fps: float = 10.0
) -> SyntheticLoad:
    """Messages of ``live_tracks`` walkers seen by ``cameras`` cameras for ``frames`` frames."""
    if live_tracks < 1 or cameras < 1 or frames < 1:
        raise ValueError("live_tracks, cameras and frames must be at least 1.")
    rng = np.random.default_rng(seed)
    side = float(np.sqrt(live_tracks * SQUARE_METRES_PER_PERSON))
    plane = PlaneSpec(1, (-1.0, -1.0), side + 2.0, side + 2.0, bits=16)
    planes = PlaneSet([plane])
    camera_ids = [f"camera{index + 1}" for index in range(cameras)]
    position = rng.uniform(0.0, side, size=(live_tracks, 2))
    heading = rng.uniform(0.0, 2 * np.pi, size=live_tracks)
    velocity = WALKING_SPEED * np.column_stack([np.cos(heading), np.sin(heading)])
    instants = []
    for frame in range(frames):
        timestamp = frame / fps
        messages = []
        for name in camera_ids:
            seen = rng.random(live_tracks) < DETECTION_PROBABILITY
            measured = position[seen] + rng.normal(0.0, NOISE_M, size=(int(seen.sum()), 2))
            colour, _ = plane.encode(np.clip(measured, 0.0, side))
            count = len(colour)
            centre_x = rng.uniform(100, 1800, size=count)
            xyxy = np.column_stack([centre_x - 20, np.full(count, 300.0), centre_x + 20,
                                    np.full(count, 420.0)])
            messages.append(CameraMessage(
                name, frame, timestamp, frame, xyxy, np.ones(count),
                np.zeros(count, np.int64), colour.astype(np.int64),
            ))
        instants.append((timestamp, messages))
        position = position + velocity / fps
        bounce = (position < 0) | (position > side)
        velocity[bounce] *= -1
        position = np.clip(position, 0.0, side)
    return SyntheticLoad(planes, camera_ids, instants)


def measure_throughput(
    live_tracks: int,
    cameras: int,
    frames: int = 60,
    seed: int = 0,
    matcher: str = "fusion",
    repeats: int = 3,
    warmup_frames: int = 5,
) -> dict:
    """Detections per second of a matcher on a synthetic load (one core, median of repeats).

    The first ``warmup_frames`` frames (track births) are processed untimed. Each run is timed
    in wall seconds and in CPU seconds of this process (:func:`time.process_time`: every
    thread's, BLAS's too); on a machine other jobs load, wall time grows with their share of
    the cores, CPU time much less (caches and memory bandwidth are shared still).

    Returns:
        ``{"matcher", "live_tracks", "cameras", "frames", "detections_per_frame",
        "detections_per_second", "milliseconds_per_frame", "cpu_milliseconds_per_frame",
        "cpu_microseconds_per_detection", "cpu_share", "repeats", "final_tracks"}``: wall
        figures are the median run's by wall time, CPU figures the median run's by CPU
        time; ``cpu_share`` is the CPU seconds over the wall seconds of the runs (below 1:
        the process waited for a core).
    """
    load = synthetic_load(live_tracks, cameras, frames + warmup_frames, seed)
    timed = load.instants[warmup_frames:]
    detections = sum(len(message) for _, messages in timed for message in messages)
    durations, cpu_durations = [], []
    final_tracks = 0
    for _ in range(repeats):
        instance = make_matcher(matcher, load.planes, load.camera_ids)
        for timestamp, messages in load.instants[:warmup_frames]:
            instance.update(timestamp, messages)
        start, cpu_start = time.perf_counter(), time.process_time()
        for timestamp, messages in timed:
            output = instance.update(timestamp, messages)
        cpu_durations.append(time.process_time() - cpu_start)
        durations.append(time.perf_counter() - start)
        final_tracks = len(output)
    seconds = statistics.median(durations)
    cpu_seconds = statistics.median(cpu_durations)
    return {
        "matcher": matcher,
        "live_tracks": live_tracks,
        "cameras": cameras,
        "frames": len(timed),
        "detections_per_frame": detections / len(timed),
        "detections_per_second": detections / seconds,
        "milliseconds_per_frame": 1000.0 * seconds / len(timed),
        "cpu_milliseconds_per_frame": 1000.0 * cpu_seconds / len(timed),
        "cpu_microseconds_per_detection": 1e6 * cpu_seconds / max(1, detections),
        "cpu_share": sum(cpu_durations) / max(sum(durations), 1e-9),
        "repeats": repeats,
        "final_tracks": final_tracks,
    }


def oracle_tracks(
    scene,
    references,
    sigma_m: float = 0.03,
    sigma_per_distance: float = 0.03,
    acceleration_sigma: float = 1.0,
    lateral_sigma_m: float | None = None,
    lateral_per_distance: float | None = None,
    model_acceleration_factors: tuple[float, ...] = (0.25, 2.0),
    model_sojourn_s: tuple[float, ...] = (10.0, 2.0),
):
    """An upper bound for any location-only tracker: identities taken from the ground truth.

    Each detection is located through the colour path exactly as the matchers see it; the
    detections of one ground-truth object at one instant are fused with inverse-covariance
    weights, and each object's fused positions are smoothed by the same constant-velocity
    Kalman filter the fusion tracker uses. A detection's variance is
    ``sigma_m**2 + (sigma_per_distance * distance)**2`` in every direction, or, when
    ``lateral_sigma_m`` or ``lateral_per_distance`` is given, that along the ray from its
    camera and ``lateral_sigma_m**2 + (lateral_per_distance * distance)**2`` across it (the
    fusion tracker's noise model). The motion model is the tracker's interacting multiple
    models (``model_acceleration_factors`` times ``acceleration_sigma``, ``model_sojourn_s``;
    ``(1.0,)`` for a single constant-velocity filter). No tracker that only sees these
    colours can associate better; its localisation can only be better by smoothing with
    look-ahead.
    False-positive detections (object id -1) are ignored.

    Returns:
        :class:`Tracks` with the ground-truth identities.
    """

    anisotropic = lateral_sigma_m is not None or lateral_per_distance is not None
    lateral_base = sigma_m if lateral_sigma_m is None else lateral_sigma_m
    lateral_slope = sigma_per_distance if lateral_per_distance is None else lateral_per_distance
    frames, identities, positions, covariances = [], [], [], []
    for index, frame in enumerate(scene.frames.tolist()):
        for camera, detections, reference in zip(
            scene.cameras, scene.detections[index], references, strict=True
        ):
            message = make_message(camera.name, index, 0.0, frame, detections, reference)
            world_xy, valid, _ = reference.planes.decode(message.colour)
            valid &= detections.object_id >= 0
            offset = world_xy[valid] - camera.centre[:2]
            distance = np.linalg.norm(offset, axis=1)
            direction = offset / np.maximum(distance, 1e-9)[:, None]
            along = sigma_m**2 + (sigma_per_distance * distance) ** 2
            lateral = (
                lateral_base**2 + (lateral_slope * distance) ** 2 if anisotropic else along
            )
            frames.append(np.full(int(valid.sum()), frame))
            identities.append(detections.object_id[valid])
            positions.append(world_xy[valid])
            covariances.append(ray_covariance(direction, along, lateral))
    frame = np.concatenate(frames)
    identity = np.concatenate(identities)
    position = np.concatenate(positions)
    keys, inverse = np.unique(np.column_stack([identity, frame]), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    fused, fused_covariance, _ = fuse(inverse, len(keys), position, np.concatenate(covariances))
    seconds = dict(zip(scene.frames.tolist(), scene.timestamps.tolist(), strict=True))
    rows = []
    for object_id in np.unique(keys[:, 0]).tolist():
        mine = np.flatnonzero(keys[:, 0] == object_id)  # sorted by frame
        models = len(model_sojourn_s)
        sojourn = np.asarray(model_sojourn_s, np.float64)
        sigma = acceleration_sigma * np.asarray(model_acceleration_factors, np.float64)[None]
        state = np.repeat(np.array([[*fused[mine[0]], 0.0, 0.0]])[:, None], models, axis=1)
        covariance = np.repeat(
            kalman.initial_covariance(1, fused_covariance[mine[:1]], 1.5)[:, None], models, 1
        )
        probability = kalman.stationary_probability(sojourn)[None]
        previous = seconds[int(keys[mine[0], 1])]
        for row in mine.tolist():
            now = seconds[int(keys[row, 1])]
            state, covariance, probability = kalman.predict_models(
                state, covariance, probability, now - previous, sigma, sojourn
            )
            state, covariance, probability = kalman.update_models(
                state, covariance, probability, fused[row:row + 1],
                fused_covariance[row:row + 1],
            )
            previous = now
            combined, _ = kalman.combine(state, covariance, probability)
            rows.append((int(keys[row, 1]), now, object_id, combined[0, 0], combined[0, 1]))
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    return Tracks(
        frame=table[:, 0].astype(np.int64), timestamp=table[:, 1],
        track_id=table[:, 2].astype(np.int64), world_xy=table[:, 3:5],
    )
