"""Synthetic crowds for identity checks where it is hard: dense, and through distorting lenses.

Two worlds, both of people wandering (:class:`~cblrs.datasets.paths.RandomWalkPath`):

* :func:`crowd_world`: many people in WILDTRACK's annotated 12 x 36 m area, seen by WILDTRACK's
  own seven calibrated cameras (read from the data set folder), at a video rate of 10 fps.
  With 60 people a neighbour is often closer than a metre, and their noisy foot points
  overlap along the viewing rays (the hard case of a crowd).
* :func:`distorted_world`: people on a 30 x 20 m square seen by six cameras whose lenses have
  strong barrel distortion (``k1 = -0.3``); their boxes are in distorted pixels, as a
  wide-angle camera delivers them, and the reference images bake the distortion in.

Both are deterministic for a seed, like every synthetic world.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cblrs.camera import Camera
from cblrs.datasets.paths import RandomWalkPath
from cblrs.datasets.scene import Scene
from cblrs.datasets.synthetic import MovingObject, SyntheticWorld, WorldSpec, class_size

WILDTRACK_AREA = (-3.0, -9.0, 9.0, 27.0)
"""WILDTRACK's annotated ground area (x_min, y_min, x_max, y_max), metres."""

BARREL_K1 = -0.3
"""Radial distortion of the distorted world's lenses (OpenCV's k1)."""


def _walkers(
    rng: np.random.Generator, count: int, area: tuple[float, float, float, float],
    first_id: int = 1,
) -> list[MovingObject]:
    x_min, y_min, x_max, y_max = area
    objects = []
    for index in range(count):
        start = (float(rng.uniform(x_min + 0.5, x_max - 0.5)),
                 float(rng.uniform(y_min + 0.5, y_max - 0.5)))
        path = RandomWalkPath(
            start=start, area=area, speed=float(rng.uniform(0.8, 1.5)),
            seed=int(rng.integers(2**31)),
        )
        objects.append(MovingObject(first_id + index, "person", class_size("person", rng), path))
    return objects


def crowd_world(
    cameras: list[Camera], seed: int = 0, people: int = 60, duration_s: float = 30.0,
    fps: float = 10.0,
) -> WorldSpec:
    """``people`` wandering in WILDTRACK's annotated area, seen by ``cameras``.

    Args:
        cameras: posed cameras, e.g. ``load_scene(wildtrack).cameras``.
        seed: seed of the starts, speeds, sizes and walks.
        people: how many people (all present the whole time).
        duration_s, fps: length and frame rate (video rate; WILDTRACK annotates 2 fps).
    """
    rng = np.random.default_rng(seed)
    x_min, y_min, x_max, y_max = WILDTRACK_AREA
    return WorldSpec(
        name="crowd",
        cameras=tuple(cameras),
        objects=tuple(_walkers(rng, people, WILDTRACK_AREA)),
        # WILDTRACK's plane: the annotated area with a 2 m margin.
        area=(x_min - 2.0, y_min - 2.0, x_max + 2.0, y_max + 2.0),
        duration_s=duration_s,
        fps=fps,
    )


def distorted_world(
    seed: int = 0, people: int = 40, duration_s: float = 30.0, fps: float = 10.0,
    k1: float = BARREL_K1,
) -> WorldSpec:
    """``people`` wandering on a 30 x 20 m square seen by six barrel-distorted cameras.

    Args:
        seed: seed of the starts, speeds, sizes and walks.
        people: how many people.
        duration_s, fps: length and frame rate.
        k1: the lenses' radial distortion (negative: barrel).
    """
    rng = np.random.default_rng(seed)
    walk_area = (-15.0, -10.0, 15.0, 10.0)
    size = (1280, 720)
    distortion = np.array([k1, 0.0, 0.0, 0.0])
    placements = (
        (-19.0, 0.0), (19.0, 0.0), (-9.0, 14.0), (9.0, -14.0), (9.0, 14.0), (-9.0, -14.0),
    )
    cameras = tuple(
        Camera.from_pose(
            f"D{index + 1}", (x, y, 6.0), math.degrees(math.atan2(-y, -x)), 30.0, 560.0, size,
            distortion=distortion,
        )
        for index, (x, y) in enumerate(placements)
    )
    return WorldSpec(
        name="distorted",
        cameras=cameras,
        objects=tuple(_walkers(rng, people, walk_area)),
        area=(-20.0, -15.0, 20.0, 15.0),
        duration_s=duration_s,
        fps=fps,
    )


def make_crowd_scene(
    wildtrack: str | Path, seed: int = 0, people: int = 60, fps: float = 10.0
) -> Scene:
    """The :class:`Scene` of :func:`crowd_world` with the cameras of a WILDTRACK folder."""
    # lazy: multiview pulls the data-set readers, needed only for this scene
    from cblrs.datasets.multiview import load_scene

    cameras = load_scene(wildtrack).cameras
    return SyntheticWorld(crowd_world(cameras, seed, people, fps=fps)).scene()


def make_distorted_scene(seed: int = 0, people: int = 40) -> Scene:
    """The :class:`Scene` of :func:`distorted_world`."""
    return SyntheticWorld(distorted_world(seed, people)).scene()
