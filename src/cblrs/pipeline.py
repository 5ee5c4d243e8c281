"""The whole pipeline on a scene, in process: render -> camera messages -> matcher -> tracks.

Each camera turns its detections into a :class:`CameraMessage` through its own colour
reference image (:func:`cblrs.edge.make_message`), exactly as an edge device would; the
matcher only ever sees colours. Messages reach the matcher through the same
:class:`~cblrs.runtime.matcher.ordering.Orderer` as in the matcher service, in capture-time order,
so the in-process tracks equal the service's on the same messages. A
:class:`~cblrs.datasets.clocks.ClockSimulation` gives the cameras their own clocks, frame
rates and lost messages.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cblrs.arrays import unique_integers
from cblrs.datasets.clocks import ClockSimulation, camera_clocks
from cblrs.datasets.scene import Scene
from cblrs.detections import CameraMessage, Tracks
from cblrs.edge import Targeter, make_messages
from cblrs.errors import DatasetError
from cblrs.matching import DEFAULT_MATCHER, Matcher, make_matcher
from cblrs.plane import PlaneSet
from cblrs.reference import OnDemandReference, Reference, ReferenceImage, render_reference
from cblrs.runtime.matcher.ordering import Orderer

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TrackingResult:
    """What :func:`track_scene` produced.

    Attributes:
        tracks: one row per (frame, track), world metres, the scene's native frame numbers.
        references: the reference of each camera (scene camera order; rendered where read
            unless rendered images were given).
        message_count: camera messages sent (one per camera and frame).
        detection_count: detections in those messages (with or without a location).
        matcher_seconds: time spent inside the matcher's ``update`` calls.
        total_seconds: wall time of the whole call, rendering included.
        render_seconds: time spent rendering reference images (0 when they were given).
        captured_frames: (F,) int64 the scene frames of which some camera's message reached
            the matcher (the instants there is anything to report; all frames unless a
            clock simulation changed frame rates or lost messages).
        clocks: the fusion tracker's clock report per camera (estimated offset, whether it is
            beyond the tolerance, ...; see :meth:`cblrs.matching.FusionTracker.clock_report`);
            None for other matchers.
        late_messages: messages the ordering received after their window had gone.
    """

    tracks: Tracks
    references: list[Reference]
    message_count: int
    detection_count: int
    matcher_seconds: float
    total_seconds: float
    render_seconds: float = 0.0
    captured_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    clocks: dict[str, dict[str, Any]] | None = None
    late_messages: int = 0


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


def scene_references(scene: Scene, bits: int = 16) -> list[OnDemandReference]:
    """Every camera's reference of the scene's ground plane, rendered where it is read.

    The colours are those of :func:`render_scene_references`' images; only the pixels the
    cameras read are rendered and nothing of the size of a frame is kept (a 16-bit
    1920 x 1080 image is 12 MB), which is what a simulated run of cameras needs.
    """
    planes = scene_planes(scene, bits)
    return [OnDemandReference(camera, planes) for camera in scene.cameras]


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
            # lazy: it needs the synthetic world's class sizes; the box targeting does not
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
    references: Sequence[Reference],
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
    order = np.argsort(scene.timestamps, kind="stable").tolist()
    frames = [
        (sequence, float(scene.timestamps[index]), int(scene.frames[index]))
        for sequence, index in enumerate(order)
    ]
    # Each camera's frames at once (the same messages as frame by frame, one lookup).
    per_camera = [
        make_messages(
            name, frames, [scene.detections[index][camera] for index in order], reference,
            targeter=targeter, drop_hidden_feet=drop_hidden_feet,
        )
        for camera, (name, reference, targeter) in enumerate(
            zip(scene.camera_names, references, chosen, strict=True)
        )
    ]
    for position, (_, timestamp, _) in enumerate(frames):
        yield timestamp, [messages[position] for messages in per_camera]


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
    start = time.perf_counter()
    parts.append(flush_matcher(matcher))
    seconds += time.perf_counter() - start
    return Tracks.concatenate(parts), seconds, message_count, detection_count


def flush_matcher(matcher: Matcher) -> Tracks:
    """The rows of what a matcher still holds at the end of a stream (none if it holds none)."""
    flush = getattr(matcher, "flush", None)
    return flush() if flush is not None else Tracks.empty()


def camera_messages(
    scene: Scene,
    references: Sequence[Reference],
    targeters: Sequence[Targeter] | None = None,
    clocks: ClockSimulation | None = None,
    drop_hidden_feet: bool = False,
) -> list[CameraMessage]:
    """Every camera's messages in the order a matcher receives them: by timestamp, then camera.

    Without ``clocks`` every camera sends one message per scene frame stamped with the frame's
    time (as :func:`scene_messages`); with it, each camera keeps its own frames and clock.
    ``drop_hidden_feet`` is :func:`cblrs.edge.make_message`'s.
    """
    if clocks is None or (clocks.synchronised and not clocks.epoch_s):
        return [message for _, messages in scene_messages(
            scene, references, targeters, drop_hidden_feet) for message in messages]
    if len(references) != len(scene.cameras):
        raise DatasetError(
            f"need one reference image per camera ({len(scene.cameras)}), got {len(references)}."
        )
    chosen: list[Targeter | None] = (
        [None] * len(scene.cameras) if targeters is None else list(targeters)
    )
    epoch = clocks.epoch_s
    timed: list[tuple[float, int, CameraMessage]] = []
    for camera_index, (clock, reference, targeter) in enumerate(
        zip(camera_clocks(scene, clocks), references, chosen, strict=True)
    ):
        indices = clock.frame_index.tolist()
        frames = [
            (sequence, epoch + recorded, int(scene.frames[index]))
            for sequence, (index, recorded) in enumerate(
                zip(indices, clock.timestamp.tolist(), strict=True)
            )
        ]
        messages = make_messages(
            clock.camera, frames, [scene.detections[index][camera_index] for index in indices],
            reference, targeter=targeter, drop_hidden_feet=drop_hidden_feet,
        )
        timed.extend(
            (message.timestamp, camera_index, message) for message in messages
        )
    timed.sort(key=lambda item: (item[0], item[1]))
    return [message for _, _, message in timed]


def ordered_windows(
    messages: Iterable[CameraMessage], camera_ids: Sequence[str]
) -> Iterator[tuple[float, list[CameraMessage]]]:
    """Release messages (each camera's in capture order) in windows, as the matcher service
    does: through an :class:`~cblrs.runtime.matcher.ordering.Orderer`.

    Yields:
        ``(timestamp, messages)`` per window, in time order (the input to ``update``).
    """

    # Nothing here is ever silent for long: the timeout is only for live cameras.
    orderer = Orderer(camera_ids, timeout_s=1e9)
    for message in messages:
        if orderer.is_late(message.timestamp):  # cannot happen in capture order
            continue
        orderer.add(message, 0.0)
        yield from orderer.release(0.0)
    yield from orderer.release(0.0, force=True)


def track_scene(
    scene: Scene,
    matcher: str | Matcher = DEFAULT_MATCHER,
    references: Sequence[Reference] | None = None,
    bits: int = 16,
    progress: bool = False,
    targeting: str | Sequence[Targeter] = "box",
    drop_hidden_feet: bool = False,
    clocks: ClockSimulation | None = None,
    **matcher_options: Any,
) -> TrackingResult:
    """Track a scene end to end through the colour path.

    Args:
        scene: cameras, per-frame detections and the ground plane.
        matcher: a matcher name (``"fusion"``, ``"paper"``) or a ready matcher instance.
        references: reference images per camera; when None, each camera's is rendered
            where it is read (:func:`scene_references`).
        bits: bit depth of the references (ignored when ``references`` are given).
        progress: show a progress bar on stderr (terminals only).
        targeting: ``"box"`` (fixed per-class targeting positions, the default),
            ``"geometric"`` (a :class:`cblrs.geometric_targeting.GeometricTargeter` per
            camera: calibration and class size priors choose the footprint centre; needs
            posed cameras), or one targeter object per camera.
        drop_hidden_feet: no location for boxes whose feet a nearer box hides; use it for
            a real detector's boxes (see :func:`cblrs.edge.make_message`).
        clocks: simulate cameras with their own clocks, frame rates and lost messages
            (:class:`~cblrs.datasets.clocks.ClockSimulation`); None: one synchronised capture.
        **matcher_options: options for :func:`make_matcher`. For ``"fusion"`` the cameras'
            ground positions are passed as ``camera_positions`` unless given (the noise
            model grows with distance from the camera), and ``vehicle_footprint`` is off
            unless given when ``targeting`` is not ``"box"`` (its targets are not the
            fixed box positions the footprint stage assumes).

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
        references = scene_references(scene, bits)
        render_seconds = time.perf_counter() - start
    references = list(references)
    if isinstance(matcher, str):
        if matcher == "fusion" and "camera_positions" not in matcher_options:
            matcher_options["camera_positions"] = camera_positions(scene)
        if matcher == "fusion" and targeting != "box":
            # Other targeting already aims at the footprint centre (or somewhere the
            # matcher cannot know): the matcher must not move the detections again.
            matcher_options.setdefault("vehicle_footprint", False)
        matcher = make_matcher(
            matcher, references[0].planes if references else scene_planes(scene, bits),
            scene.camera_names, **matcher_options,
        )
    elif matcher_options:
        raise ValueError("matcher options are only accepted with a matcher name.")
    set_views = getattr(matcher, "set_views", None)
    if set_views is not None:
        # Where each camera sees the ground (multi-view confirmation), as `cblrs matcher`
        # tells its tracker from the same references.
        set_views(references)
    messages: Iterable[CameraMessage] = camera_messages(
        scene, references, scene_targeters(scene, targeting), clocks, drop_hidden_feet
    )
    captured = unique_integers([message.frame for message in messages])
    if progress and sys.stderr.isatty():
        # lazy: tqdm reads its version through importlib.metadata (~20 ms); only a bar needs it
        from tqdm import tqdm

        messages = tqdm(messages, desc="tracking", leave=False)
    tracks, matcher_seconds, message_count, detection_count = run_matcher(
        matcher, ordered_windows(messages, scene.camera_names)
    )
    total = time.perf_counter() - start
    logger.debug(
        "tracked %s: %d rows, %d messages, %d detections, matcher %.3f s, total %.3f s",
        scene.name, len(tracks), message_count, detection_count, matcher_seconds, total,
    )
    report = getattr(matcher, "clock_report", None)
    return TrackingResult(
        tracks=tracks,
        references=references,
        message_count=message_count,
        detection_count=detection_count,
        matcher_seconds=matcher_seconds,
        total_seconds=total,
        render_seconds=render_seconds,
        captured_frames=captured.astype(np.int64),
        clocks=report() if report is not None else None,
    )
