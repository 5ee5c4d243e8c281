"""The two preset synthetic worlds, ``roundabout`` and ``plaza``, and the scenes made from them.

:func:`roundabout_world` and :func:`plaza_world` each build a
:class:`~cblrs.datasets.synthetic.WorldSpec` from the types of :mod:`cblrs.datasets.synthetic`;
:func:`make_world` and :func:`make_scene` pick one by name (:data:`PRESETS`), deterministic for
a seed.
"""

from __future__ import annotations

import numpy as np

from cblrs.camera import Camera
from cblrs.datasets.boxes3d import class_size
from cblrs.datasets.paths import LanePath, LoopPath, Path, RandomWalkPath
from cblrs.datasets.scene import Scene
from cblrs.datasets.synthetic import (
    GroundMarking,
    MovingObject,
    Structure,
    SyntheticWorld,
    WorldSpec,
)
from cblrs.errors import DatasetError

_IMAGE_SIZE = (1280, 720)


def roundabout_world(
    seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """Two cameras over a roundabout; one car drives a full circle (the paper's hand-over case).

    The cameras stand on masts west and east of the roundabout and look across it; the
    monument on the central island (a 10 x 10 x 7 m block set diagonally) hides the
    far side of the ring from each. The car (radius 12 m, 7.5 m/s, counter-clockwise)
    starts and ends where only camera A sees it; on the way it passes an overlap (north or
    south, seen by both), the stretch only camera B sees, and a second overlap, so its
    identity has to be handed from A to B and back. One lap takes about 10 s; the default
    duration (10.6 s) covers it.
    """
    rng = np.random.default_rng(seed)
    radius, speed = 12.0, 7.5
    # A small seeded jitter of the mounting so that seeds differ without moving the overlaps.
    jitter = rng.uniform(-0.3, 0.3, size=4)
    cameras = (
        Camera.from_pose(
            "A", (-24.0, -2.0 + jitter[0], 9.0), 4.8 + jitter[1], 22.0, 900.0, _IMAGE_SIZE
        ),
        Camera.from_pose(
            "B", (24.0, 2.0 + jitter[2], 9.0), 184.8 + jitter[3], 22.0, 900.0, _IMAGE_SIZE
        ),
    )
    car = MovingObject(
        1, "car", class_size("car", rng), LoopPath((0.0, 0.0), radius, speed, start_angle_deg=160.0)
    )
    monument = (Structure((0.0, 0.0), (10.0, 10.0, 7.0), 45.0, "monument"),)
    return WorldSpec(
        name="roundabout",
        cameras=cameras,
        objects=(car,),
        area=(-20.0, -20.0, 20.0, 20.0),
        duration_s=10.6 if duration_s is None else duration_s,
        fps=10.0 if fps is None else fps,
        structures=monument,
        markings=roundabout_markings(radius),
    )


def roundabout_markings(radius: float) -> tuple[GroundMarking, ...]:
    """Asphalt ring, kerbs and a green central island of a roundabout (for pictures only)."""
    angles = np.linspace(0, 2 * np.pi, 97)[:-1]

    def circle(r: float) -> tuple[tuple[float, float], ...]:
        return tuple((float(r * np.cos(a)), float(r * np.sin(a))) for a in angles)

    return (
        GroundMarking(circle(radius + 2.2), (70, 72, 76)),
        GroundMarking(circle(radius - 2.0), (215, 215, 210)),
        GroundMarking(circle(radius - 2.4), (92, 140, 70)),
    )


def plaza_world(
    seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """Four corner cameras over a 30 x 20 m plaza with a road along its south side.

    Twenty people wander (random walks that cross each other), six more walk straight across
    at staggered times (arrivals and departures), and two cars drive along the road,
    hiding people behind them for a while.
    """
    rng = np.random.default_rng(seed)
    duration = 30.0 if duration_s is None else duration_s
    cameras = tuple(
        Camera.from_pose(name, (x, y, 8.0), pan, 32.0, 820.0, _IMAGE_SIZE)
        for name, x, y, pan in (
            ("NW", -17.0, 12.0, -35.0),
            ("NE", 17.0, 12.0, -145.0),
            ("SE", 17.0, -15.0, 140.0),
            ("SW", -17.0, -15.0, 40.0),
        )
    )
    walk_area = (-13.0, -8.0, 13.0, 9.0)
    objects: list[MovingObject] = []
    for index in range(20):
        start = (
            rng.uniform(walk_area[0] + 2, walk_area[2] - 2),
            rng.uniform(walk_area[1] + 2, walk_area[3] - 2),
        )
        path = RandomWalkPath(
            start=start,
            area=walk_area,
            speed=float(rng.uniform(0.9, 1.6)),
            seed=int(rng.integers(2**31)),
        )
        objects.append(MovingObject(index + 1, "person", class_size("person", rng), path))
    crossings = [
        ((-15.0, -6.0), (15.0, 8.0)),
        ((15.0, 4.0), (-15.0, -3.0)),
        ((-6.0, 10.0), (4.0, -9.0)),
        ((8.0, -9.0), (-3.0, 10.0)),
        ((-15.0, 1.0), (15.0, 0.0)),
        ((15.0, -7.0), (-15.0, 6.0)),
    ]
    for index, (start, end) in enumerate(crossings):
        lane: Path = LanePath(
            start, end, float(rng.uniform(1.1, 1.6)), start_s=float(index * duration / 7)
        )
        objects.append(MovingObject(21 + index, "person", class_size("person", rng), lane))
    roads = [
        ((-40.0, -11.0), (40.0, -11.0), 0.1 * duration),
        ((40.0, -13.0), (-40.0, -13.0), 0.4 * duration),
    ]
    for index, (start, end, start_s) in enumerate(roads):
        road: Path = LanePath(start, end, float(rng.uniform(5.0, 7.0)), start_s=float(start_s))
        objects.append(MovingObject(101 + index, "car", class_size("car", rng), road))
    return WorldSpec(
        name="plaza",
        cameras=cameras,
        objects=tuple(objects),
        area=(-20.0, -16.0, 20.0, 14.0),
        duration_s=duration,
        fps=5.0 if fps is None else fps,
    )


PRESETS = {"roundabout": roundabout_world, "plaza": plaza_world}


def make_world(
    preset: str, seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> WorldSpec:
    """The :class:`WorldSpec` of a preset (see :data:`PRESETS`); None keeps its defaults."""
    try:
        builder = PRESETS[preset]
    except KeyError:
        raise DatasetError(
            f"unknown synthetic preset {preset!r}; known presets: {', '.join(sorted(PRESETS))}."
        ) from None
    return builder(seed=seed, duration_s=duration_s, fps=fps)


def make_scene(
    preset: str, seed: int = 0, duration_s: float | None = None, fps: float | None = None
) -> Scene:
    """A synthetic :class:`Scene` from a preset, deterministic for a seed.

    Args:
        preset: ``"roundabout"`` or ``"plaza"``.
        seed: seed of every random choice (sizes, walks, start times).
        duration_s: sequence length in seconds; None uses the preset's default.
        fps: frame rate; None uses the preset's default.

    Example:
        >>> scene = make_scene("roundabout")
        >>> scene.camera_names, round(scene.frame_interval, 3)
        (['A', 'B'], 0.1)
    """
    return SyntheticWorld(make_world(preset, seed, duration_s, fps)).scene()
