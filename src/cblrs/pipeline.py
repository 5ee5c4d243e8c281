"""The whole pipeline on a scene, in process: render -> camera messages -> matcher -> tracks.

Each camera turns its detections into a :class:`CameraMessage` through its own colour
reference image (:func:`cblrs.edge.make_message`), exactly as an edge device would; the
matcher only ever sees colours. Messages are grouped by capture timestamp and fed to the
matcher in time order.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cblrs.datasets.scene import Scene
from cblrs.detections import CameraMessage, Tracks
from cblrs.edge import Targeter, make_message
from cblrs.errors import DatasetError
from cblrs.matching import DEFAULT_MATCHER, Matcher, make_matcher
from cblrs.plane import PlaneSet
from cblrs.reference import ReferenceImage, render_reference

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TrackingResult:
    """What :func:`track_scene` produced.

    Attributes:
        tracks: one row per (frame, track), world metres, the scene's native frame numbers.
        references: the reference image of each camera (scene camera order).
        message_count: camera messages sent (one per camera and frame).
        detection_count: detections in those messages (with or without a location).
        matcher_seconds: time spent inside the matcher's ``update`` calls.
        total_seconds: wall time of the whole call, rendering included.
        render_seconds: time spent rendering reference images (0 when they were given).
    """

    tracks: Tracks
    references: list[ReferenceImage]
    message_count: int
    detection_count: int
    matcher_seconds: float
    total_seconds: float
    render_seconds: float = 0.0


def scene_planes(scene: Scene, bits: int = 16) -> PlaneSet:
    """The scene's ground plane at the requested bit depth."""
    return PlaneSet([replace(scene.plane, bits=bits)])


def render_scene_references(scene: Scene, bits: int = 16) -> list[ReferenceImage]:
    """Render every camera's reference image of the scene's ground plane.

    Args:
        scene: the scene (its ``plane`` is the encoded area).
        bits: 8 or 16 bits per channel.

    Returns:
        One reference image per camera, in the scene's camera order.
    """
    planes = scene_planes(scene, bits)
    return [render_reference(camera, planes) for camera in scene.cameras]


def camera_positions(scene: Scene) -> dict[str, tuple[float, float, float]]:
    """Positions ``{name: (x, y, height)}`` metres of the scene's cameras that have a pose.

    The matcher uses them to let measurement noise grow with distance from the camera,
    elongated along the viewing ray, and more so for low cameras.
    Camera placement is configuration the central node has anyway (it is needed to render
    the reference images); no per-frame data beyond colours is involved.
    """
    return {
        camera.name: (float(camera.centre[0]), float(camera.centre[1]), float(camera.centre[2]))
        for camera in scene.cameras
        if camera.has_pose
    }


def scene_targeters(
    scene: Scene, targeting: str | Sequence[Targeter]
) -> list[Targeter] | None:
    """Per-camera targeters for ``targeting`` (None for the fixed box targeting)."""
    if isinstance(targeting, str):
        if targeting == "box":
            return None
        if targeting == "geometric":
            from cblrs.geometric_targeting import GeometricTargeter

            return [GeometricTargeter(camera) for camera in scene.cameras]
        raise ValueError(f"targeting must be 'box' or 'geometric', got {targeting!r}")
    targeters = list(targeting)
    if len(targeters) != len(scene.cameras):
        raise ValueError(
            f"need one targeter per camera ({len(scene.cameras)}), got {len(targeters)}"
        )
    return targeters


def scene_messages(
    scene: Scene,
    references: Sequence[ReferenceImage],
    targeters: Sequence[Targeter] | None = None,
    drop_hidden_feet: bool = False,
) -> Iterator[tuple[float, list[CameraMessage]]]:
    """The camera messages of each frame, as ``(timestamp, messages)`` in time order.

    Every camera sends a message per frame, empty or not (an empty message says "I looked
    and saw nothing"). ``targeters`` (one per camera) replace the fixed box targeting;
    ``drop_hidden_feet`` is :func:`cblrs.edge.make_message`'s (for a detector's boxes).
    """
    chosen: list[Targeter | None] = (
        [None] * len(scene.cameras) if targeters is None else list(targeters)
    )
    if len(references) != len(scene.cameras):
        raise DatasetError(
            f"need one reference image per camera ({len(scene.cameras)}), got {len(references)}."
        )
    names = scene.camera_names
    order = np.argsort(scene.timestamps, kind="stable")
    for sequence, index in enumerate(order.tolist()):
        timestamp = float(scene.timestamps[index])
        frame = int(scene.frames[index])
        messages = [
            make_message(
                name, sequence, timestamp, frame, detections, reference, targeter=targeter,
                drop_hidden_feet=drop_hidden_feet,
            )
            for name, detections, reference, targeter in zip(
                names, scene.detections[index], references, chosen, strict=True
            )
        ]
        yield timestamp, messages


def run_matcher(
    matcher: Matcher, instants: Iterable[tuple[float, Sequence[CameraMessage]]]
) -> tuple[Tracks, float, int, int]:
    """Feed ``(timestamp, messages)`` instants to a matcher.

    Returns:
        ``(tracks, matcher_seconds, message_count, detection_count)``.
    """
    parts: list[Tracks] = []
    seconds = 0.0
    message_count = detection_count = 0
    for timestamp, messages in instants:
        message_count += len(messages)
        detection_count += sum(len(message) for message in messages)
        start = time.perf_counter()
        parts.append(matcher.update(timestamp, messages))
        seconds += time.perf_counter() - start
    return Tracks.concatenate(parts), seconds, message_count, detection_count


def track_scene(
    scene: Scene,
    matcher: str | Matcher = DEFAULT_MATCHER,
    references: Sequence[ReferenceImage] | None = None,
    bits: int = 16,
    progress: bool = False,
    targeting: str | Sequence[Targeter] = "box",
    drop_hidden_feet: bool = False,
    **matcher_options: Any,
) -> TrackingResult:
    """Track a scene end to end through the colour path.

    Args:
        scene: cameras, per-frame detections and the ground plane.
        matcher: a matcher name (``"fusion"``, ``"paper"``) or a ready matcher instance.
        references: reference images per camera; rendered when None.
        bits: bit depth for rendering (ignored when ``references`` are given).
        progress: show a progress bar on stderr (terminals only).
        targeting: ``"box"`` (fixed per-class targeting positions, the default),
            ``"geometric"`` (a :class:`cblrs.geometric_targeting.GeometricTargeter` per
            camera: calibration and class size priors choose the footprint centre; needs
            posed cameras), or one targeter object per camera.
        drop_hidden_feet: no location for boxes whose feet a nearer box hides; use it for
            a real detector's boxes (see :func:`cblrs.edge.make_message`).
        **matcher_options: options for :func:`make_matcher`. For ``"fusion"`` the cameras'
            ground positions are passed as ``camera_positions`` unless given (the noise
            model grows with distance from the camera).

    Returns:
        The tracks and bookkeeping; see :class:`TrackingResult`.

    Example:
        >>> from cblrs.datasets import load_scene  # doctest: +SKIP
        >>> result = track_scene(load_scene("../shared/data/wildtrack"))  # doctest: +SKIP
        >>> result.tracks.track_id.max()  # doctest: +SKIP
    """
    start = time.perf_counter()
    render_seconds = 0.0
    if references is None:
        references = render_scene_references(scene, bits)
        render_seconds = time.perf_counter() - start
    references = list(references)
    if isinstance(matcher, str):
        if matcher == "fusion" and "camera_positions" not in matcher_options:
            matcher_options["camera_positions"] = camera_positions(scene)
        matcher = make_matcher(
            matcher, references[0].planes if references else scene_planes(scene, bits),
            scene.camera_names, **matcher_options,
        )
    elif matcher_options:
        raise ValueError("matcher options are only accepted with a matcher name.")
    instants: Iterable[tuple[float, list[CameraMessage]]] = scene_messages(
        scene, references, scene_targeters(scene, targeting), drop_hidden_feet
    )
    if progress:
        from tqdm import tqdm

        instants = tqdm(
            instants, desc="tracking", total=len(scene.frames), leave=False,
            disable=not sys.stderr.isatty(),
        )
    tracks, matcher_seconds, message_count, detection_count = run_matcher(matcher, instants)
    total = time.perf_counter() - start
    logger.debug(
        "tracked %s: %d rows, %d messages, %d detections, matcher %.3f s, total %.3f s",
        scene.name, len(tracks), message_count, detection_count, matcher_seconds, total,
    )
    return TrackingResult(
        tracks=tracks,
        references=references,
        message_count=message_count,
        detection_count=detection_count,
        matcher_seconds=matcher_seconds,
        total_seconds=total,
        render_seconds=render_seconds,
    )
