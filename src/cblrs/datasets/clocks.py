"""Simulated camera clocks: offsets, timestamp jitter, frame rates and lost messages.

Data sets capture every camera at the same instants and stamp them with one clock. Real
cameras do not: each has its own clock (NTP keeps it within milliseconds to tens of
milliseconds of the others; a misconfigured one is off by seconds), stamps each frame a
little irregularly, runs at its own frame rate, and now and then a message is lost. This
module turns a scene's ideal schedule into such a camera's, seeded and reproducibly:

* **frame rates**: camera ``c`` keeps every ``k``-th frame of the scene, ``k = scene fps /
  camera fps`` (the scene's rate must be a multiple of every camera's; the synthetic world is
  rendered at their least common multiple);
* **clock offsets**: each camera's timestamps are shifted by a constant drawn uniformly from
  ``[-offset, +offset]`` (plus any explicit per-camera error);
* **jitter**: each timestamp gets Gaussian noise of standard deviation ``jitter``;
* **lost messages**: each message is dropped with probability ``drop``.

What a camera saw does not change, only when it says it saw it (and whether the message
arrives): the capture instants are the scene's frames, so ground truth stays valid.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
from numpy.typing import NDArray

from cblrs.datasets.scene import Scene
from cblrs.errors import DatasetError


@dataclass(frozen=True)
class ClockSimulation:
    """How the cameras' clocks and frame rates depart from one synchronised capture.

    Attributes:
        offset_s: clock offsets are drawn per camera uniformly from ``[-offset_s, offset_s]``.
        jitter_s: standard deviation of each timestamp's noise, seconds.
        drop: probability that a message is lost, in [0, 1).
        camera_fps: frame rate of each camera (cycled over the cameras when shorter); empty
            keeps the scene's rate for every camera.
        clock_errors: extra offset of named cameras, seconds (a camera with a wrong clock).
        seed: seed of the offsets, jitter and losses.
        epoch_s: added to every timestamp, as a camera node replaying the scene adds its
            epoch (``epoch + recorded``, so in-process runs see the very same numbers).
    """

    offset_s: float = 0.0
    jitter_s: float = 0.0
    drop: float = 0.0
    camera_fps: tuple[float, ...] = ()
    clock_errors: Mapping[str, float] = field(default_factory=dict)
    seed: int = 0
    epoch_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("offset_s", "jitter_s"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise DatasetError(f"{name} must be a finite number >= 0, got {value!r}.")
        if not isinstance(self.drop, int | float) or not 0 <= self.drop < 1:
            raise DatasetError(f"drop must be in [0, 1), got {self.drop!r}.")
        rates = tuple(float(rate) for rate in self.camera_fps)
        if any(not math.isfinite(rate) or rate <= 0 for rate in rates):
            raise DatasetError(f"camera frame rates must be positive, got {list(rates)}.")
        object.__setattr__(self, "camera_fps", rates)
        errors = {str(name): float(value) for name, value in self.clock_errors.items()}
        if any(not math.isfinite(value) for value in errors.values()):
            raise DatasetError(f"clock errors must be finite seconds, got {errors}.")
        object.__setattr__(self, "clock_errors", errors)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise DatasetError(f"seed must be a non-negative integer, got {self.seed!r}.")

    @property
    def synchronised(self) -> bool:
        """Whether this changes nothing (one rate, no offsets, no jitter, no losses)."""
        return not (self.offset_s or self.jitter_s or self.drop or self.camera_fps
                    or any(self.clock_errors.values()))

    def scene_fps(self, default: float) -> float:
        """The frame rate a synthetic scene needs: the least common multiple of the cameras'
        rates (``default`` without camera rates)."""
        if not self.camera_fps:
            return default
        rates = [Fraction(rate).limit_denominator(1000) for rate in self.camera_fps]
        multiple = rates[0]
        for rate in rates[1:]:
            numerator = math.lcm(multiple.numerator * rate.denominator,
                                 rate.numerator * multiple.denominator)
            multiple = Fraction(numerator, multiple.denominator * rate.denominator)
        return float(multiple)


@dataclass(frozen=True, eq=False)
class CameraClock:
    """One camera's simulated schedule.

    Attributes:
        camera: the camera's name.
        offset_s: its clock offset, seconds (positive: ahead).
        frame_index: (K,) int64 indices into the scene's frames of the messages it sends.
        timestamp: (K,) float64 the timestamps it puts on them, seconds, relative to the
            scene's clock (without :attr:`ClockSimulation.epoch_s`).
    """

    camera: str
    offset_s: float
    frame_index: NDArray[np.int64]
    timestamp: NDArray[np.float64]


def camera_clocks(scene: Scene, simulation: ClockSimulation) -> list[CameraClock]:
    """Each camera's frames and timestamps under ``simulation`` (scene camera order).

    Raises:
        DatasetError: a camera's frame rate does not divide the scene's, or a clock error
            names an unknown camera.
    """
    names = scene.camera_names
    unknown = sorted(set(simulation.clock_errors) - set(names))
    if unknown:
        raise DatasetError(
            f"clock errors name unknown camera(s) {unknown}; cameras: {', '.join(names)}."
        )
    random = np.random.default_rng(np.random.SeedSequence(simulation.seed).spawn(1)[0])
    offsets = random.uniform(-simulation.offset_s, simulation.offset_s, len(names))
    interval = scene.frame_interval
    clocks = []
    for index, name in enumerate(names):
        # Draw every stream in full for every camera so that one setting does not change
        # the others' random numbers.
        jitter = random.standard_normal(len(scene.frames)) * simulation.jitter_s
        lost = random.random(len(scene.frames)) < simulation.drop
        keep = ~lost
        if simulation.camera_fps:
            rate = simulation.camera_fps[index % len(simulation.camera_fps)]
            keep &= _every(scene, rate, interval)
        offset = float(offsets[index]) + simulation.clock_errors.get(name, 0.0)
        frame_index = np.flatnonzero(keep).astype(np.int64)
        timestamp = scene.timestamps[frame_index] + offset + jitter[frame_index]
        # A camera's clock does not run backwards: jitter never reorders its own frames.
        timestamp = np.maximum.accumulate(timestamp) if len(timestamp) else timestamp
        clocks.append(CameraClock(name, offset, frame_index, timestamp))
    return clocks


def _every(scene: Scene, rate: float, interval: float) -> NDArray[np.bool_]:
    """Frames a camera at ``rate`` fps captures of a scene sampled every ``interval`` s."""
    if interval <= 0:
        return np.ones(len(scene.frames), dtype=bool)
    step = 1.0 / (rate * interval)
    if step < 1 - 1e-6 or abs(step - round(step)) > 1e-6:
        raise DatasetError(
            f"a camera at {rate:g} fps needs a scene whose frame rate ({1 / interval:g} fps) "
            "is a whole multiple of it."
        )
    position = np.rint((scene.timestamps - scene.timestamps[0]) / interval).astype(np.int64)
    return position % round(step) == 0


def parse_clock_errors(values: Sequence[str]) -> dict[str, float]:
    """``["CAM=SECONDS", ...]`` (command-line form) as ``{camera: seconds}``.

    Raises:
        DatasetError: a value is not ``NAME=NUMBER``.
    """
    errors: dict[str, float] = {}
    for value in values:
        name, separator, seconds = value.partition("=")
        try:
            if not separator or not name:
                raise ValueError
            errors[name] = float(seconds)
        except ValueError:
            raise DatasetError(
                f"a clock error must be CAMERA=SECONDS (e.g. CVLab3=2.0), got {value!r}."
            ) from None
    return errors
