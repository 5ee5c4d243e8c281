"""Options of ``cblrs track`` for unsynchronised cameras and the synthetic world.

``--clock-offset-ms``, ``--clock-jitter-ms``, ``--drop-messages``, ``--camera-fps`` and
``--clock-error`` give every camera its own clock, frame rate and lost messages
(:class:`cblrs.datasets.clocks.ClockSimulation`); ``synthetic:PRESET`` as the dataset tracks
the synthetic world instead of a folder.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from cblrs.cli.common import UsageError
from cblrs.datasets.clocks import ClockSimulation, parse_clock_errors
from cblrs.datasets.scene import Scene
from cblrs.errors import DatasetError

SYNTHETIC_PREFIX = "synthetic:"


def add_clock_options(parser: argparse.ArgumentParser) -> None:
    """Add the options that simulate unsynchronised cameras (offsets, jitter, frame rates,
    lost messages, a wrong clock)."""
    group = parser.add_argument_group(
        "unsynchronised cameras (simulated)",
        "Each camera stamps its messages with its own clock, runs at its own frame rate and "
        "loses some messages; the matcher groups them by (corrected) capture time.",
    )
    group.add_argument("--clock-offset-ms", type=float, default=0.0, metavar="MS",
                       help="per-camera clock offsets drawn uniformly from [-MS, +MS] "
                       "(default 0)")
    group.add_argument("--clock-jitter-ms", type=float, default=0.0, metavar="MS",
                       help="standard deviation of each timestamp's noise (default 0)")
    group.add_argument("--drop-messages", type=float, default=0.0, metavar="P",
                       help="probability that a camera's message is lost (default 0)")
    group.add_argument("--camera-fps", metavar="FPS[,FPS...]",
                       help="frame rate of each camera, cycled over the cameras (e.g. 10,15); "
                       "the dataset's rate must be a multiple of each (default: the dataset's)")
    group.add_argument("--clock-error", action="append", default=[], metavar="CAMERA=SECONDS",
                       help="a camera whose clock is off by SECONDS (repeatable)")
    group.add_argument("--clock-seed", type=int, default=None, metavar="S",
                       help="seed of the offsets, jitter and losses (default: --seed)")
    group.add_argument("--duration", type=float, default=30.0, metavar="SECONDS",
                       help="length of a synthetic:PRESET scene (default 30)")


def clock_simulation(args: argparse.Namespace) -> ClockSimulation | None:
    """The simulation the options ask for; None when they ask for none.

    Raises:
        UsageError: a value out of range, said in one sentence.
    """
    for name in ("clock_offset_ms", "clock_jitter_ms"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0):
            raise UsageError(f"--{name.replace('_', '-')} must be >= 0, got {value}.")
    if not 0 <= args.drop_messages < 1:
        raise UsageError(f"--drop-messages must be in [0, 1), got {args.drop_messages}.")
    rates: tuple[float, ...] = ()
    if args.camera_fps:
        try:
            rates = tuple(float(word) for word in args.camera_fps.split(",") if word.strip())
        except ValueError:
            raise UsageError(
                f"--camera-fps must be comma-separated frame rates, got {args.camera_fps!r}."
            ) from None
        if not rates or any(not (math.isfinite(rate) and rate > 0) for rate in rates):
            raise UsageError(f"--camera-fps must be positive frame rates, got {args.camera_fps!r}.")
    try:
        simulation = ClockSimulation(
            offset_s=args.clock_offset_ms / 1000, jitter_s=args.clock_jitter_ms / 1000,
            drop=args.drop_messages, camera_fps=rates,
            clock_errors=parse_clock_errors(args.clock_error),
            seed=args.seed if args.clock_seed is None else args.clock_seed,
        )
    except DatasetError as error:
        raise UsageError(str(error)) from None
    return None if simulation.synchronised else simulation


def is_synthetic(dataset: Path) -> bool:
    """Whether ``dataset`` names a synthetic scene (``synthetic:PRESET``)."""
    return str(dataset).startswith(SYNTHETIC_PREFIX)


def synthetic_scene(dataset: Path, simulation: ClockSimulation | None, duration_s: float) -> Scene:
    """The synthetic world named ``synthetic:PRESET``, rendered at a rate every camera's
    frame rate divides (the preset's own rate without ``--camera-fps``)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.presets import PRESETS, make_scene, make_world

    preset = str(dataset)[len(SYNTHETIC_PREFIX):]
    if preset not in PRESETS:
        raise UsageError(
            f"unknown synthetic preset {preset!r}; choose one of: {', '.join(sorted(PRESETS))}."
        )
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise UsageError(f"--duration must be a positive number of seconds, got {duration_s}.")
    fps = make_world(preset).fps
    if simulation is not None:
        fps = simulation.scene_fps(fps)
    return make_scene(preset, fps=fps, duration_s=duration_s)
