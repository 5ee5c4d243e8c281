"""Random walks for the analytics tests (imported by the tests, like tests/core/core_cameras)."""

from __future__ import annotations

import numpy as np

from cblrs.detections import Tracks


def random_tracks(seed: int, tracks: int = 12, steps: int = 80, rate_hz: float = 5.0) -> Tracks:
    """People walking through a 20 x 20 m square with jitter, gaps and id reuse after gaps."""
    rng = np.random.default_rng(seed)
    parts = []
    for track in range(1, tracks + 1):
        start = rng.uniform(-10, 10, 2)
        velocity = rng.normal(0, 1.2, 2)
        begin = int(rng.integers(0, steps // 2))
        length = int(rng.integers(3, steps))
        frames = np.arange(begin, begin + length)
        frames = frames[rng.random(length) > 0.15]  # missed updates
        if len(frames) > 10 and rng.random() < 0.3:  # a long gap: the id lives twice
            frames = np.concatenate([frames[:5], frames[5:] + int(4 * rate_hz)])
        seconds = frames / rate_hz
        xy = start + velocity * (seconds - seconds[0])[:, None]
        xy += rng.normal(0, 0.3, xy.shape)  # jitter across lines and borders
        parts.append(
            Tracks(frames, seconds, np.full(len(frames), track), xy,
                   class_id=np.full(len(frames), int(rng.integers(0, 2))))
        )
    tracks_all = Tracks.concatenate(parts)
    order = np.lexsort((tracks_all.track_id, tracks_all.timestamp))
    return tracks_all[order]

