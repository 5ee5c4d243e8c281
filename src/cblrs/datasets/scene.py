"""The common in-memory form of a multi-camera sequence.

Readers (WILDTRACK, MultiviewX) and the synthetic world all return a :class:`Scene`, so the
tracker, evaluation and demo never care where the data came from.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.detections import Detections, Tracks
from cblrs.errors import DatasetError
from cblrs.plane import PlaneSpec


@dataclass(frozen=True, eq=False)
class Scene:
    """Cameras, per-frame detections and ground truth of one sequence.

    Attributes:
        name: a label ("wildtrack", "roundabout", ...).
        cameras: the cameras; a camera's index here is its integer ``camera_id``.
        frames: (F,) int64 native frame numbers, increasing.
        timestamps: (F,) float64 capture time of each frame in seconds.
        detections: ``detections[f][c]`` are the boxes of camera c at frame index f, with
            ``object_id`` set to the ground-truth identity where known.
        ground_truth: world positions of every annotated object per frame (``track_id`` is
            the ground-truth identity; ``frame`` the native frame number).
        plane: a ground plane covering the scene, for rendering reference images.
    """

    name: str
    cameras: list[Camera]
    frames: NDArray[np.int64]
    timestamps: NDArray[np.float64]
    detections: list[list[Detections]]
    ground_truth: Tracks
    plane: PlaneSpec

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames, dtype=np.int64)
        timestamps = np.asarray(self.timestamps, dtype=np.float64)
        object.__setattr__(self, "frames", frames)
        object.__setattr__(self, "timestamps", timestamps)
        if frames.shape != timestamps.shape or frames.ndim != 1:
            raise DatasetError("frames and timestamps must be 1-D and of equal length.")
        if len(self.detections) != len(frames):
            raise DatasetError(
                f"detections cover {len(self.detections)} frames but the scene has {len(frames)}."
            )
        for per_camera in self.detections:
            if len(per_camera) != len(self.cameras):
                raise DatasetError(
                    f"each frame needs detections for {len(self.cameras)} cameras, "
                    f"got {len(per_camera)}."
                )

    @property
    def camera_names(self) -> list[str]:
        """The cameras' names, in the order ``camera_id`` columns index them."""
        return [camera.name for camera in self.cameras]

    @property
    def frame_interval(self) -> float:
        """Median time between frames, seconds."""
        if len(self.timestamps) < 2:
            return 0.0
        return float(np.median(np.diff(self.timestamps)))

    @property
    def frames_per_second(self) -> float | None:
        """Rate of the native frame numbers (frame units per second), None if unknown."""
        span = float(self.timestamps[-1] - self.timestamps[0]) if len(self.frames) > 1 else 0.0
        if span <= 0:
            return None
        return float(self.frames[-1] - self.frames[0]) / span

    def select_frames(self, first: int | None = None, last: int | None = None) -> Scene:
        """The sub-sequence with native frame numbers in [first, last] (inclusive)."""
        keep = np.ones(len(self.frames), dtype=bool)
        if first is not None:
            keep &= self.frames >= first
        if last is not None:
            keep &= self.frames <= last
        if not keep.any():
            raise DatasetError(
                f"no frames in {first}:{last}; the scene has frames "
                f"{self.frames.min()}..{self.frames.max()}."
            )
        indices = np.flatnonzero(keep)
        kept = set(self.frames[indices].tolist())
        truth = self.ground_truth[np.isin(self.ground_truth.frame, list(kept))]
        return replace(
            self,
            frames=self.frames[indices],
            timestamps=self.timestamps[indices],
            detections=[self.detections[i] for i in indices],
            ground_truth=truth,
        )
