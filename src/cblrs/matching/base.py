"""What every matcher shares: the interface, option errors and message decoding.

A matcher is the central node of the paper's Fig. 4. It receives :class:`CameraMessage`
objects (boxes and reference *colours*, never images), decodes the colours to world
positions with the shared :class:`PlaneSet`, and keeps global identities.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from cblrs.detections import CameraMessage, Tracks
from cblrs.errors import CblrsError
from cblrs.plane import PlaneSet

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class MatcherError(CblrsError, ValueError):
    """Bad matcher options, an unknown camera or an unusable saved state."""


@runtime_checkable
class Matcher(Protocol):
    """Online multi-camera matcher: messages in, global tracks out."""

    def update(self, timestamp: float, messages: Sequence[CameraMessage]) -> Tracks:
        """Process the messages of one released group (seconds by the cameras' clocks).

        Args:
            timestamp: the latest capture time among ``messages``, non-decreasing between
                calls; every message captured at or before it has been delivered (in this
                call or an earlier one). With synchronised cameras: the instant's time.
            messages: messages from any subset of the cameras (possibly none), captured at
                or before ``timestamp``, at most one per camera and capture time.

        Returns:
            The rows to output now, one per reported track and frame. A matcher that waits
            for late cameras (the fusion tracker) may return rows of earlier groups; an
            optional ``flush()`` method returns what it still holds at the end of a stream.
        """
        ...

    def reset(self) -> None:
        """Forget all tracks and restart identities at 1."""
        ...

    def get_state(self) -> dict:
        """A JSON-serialisable snapshot of everything the matcher remembers."""
        ...

    def set_state(self, state: dict) -> None:
        """Restore a snapshot from :meth:`get_state` (a restarted service resumes)."""
        ...


@dataclass(frozen=True, eq=False)
class Observations:
    """All decodable detections of one instant, flattened over the messages.

    Attributes:
        world_xy: (N, 2) float64 metres, decoded from the colours.
        colour: (N, 3) int64 the colours as received.
        camera: (N,) int64 index of the sending camera in the matcher's ``camera_ids``.
        xyxy: (N, 4) float64 pixel boxes.
        confidence: (N,) float64.
        class_id: (N,) int64.
    """

    world_xy: FloatArray
    colour: IntArray
    camera: IntArray
    xyxy: FloatArray
    confidence: FloatArray
    class_id: IntArray

    def __len__(self) -> int:
        return len(self.world_xy)

    def __getitem__(self, index: NDArray[np.bool_] | NDArray[np.intp]) -> Observations:
        """The detections at ``index``, an (N,) boolean mask or integer indices, every
        column alike."""
        return Observations(
            world_xy=self.world_xy[index],
            colour=self.colour[index],
            camera=self.camera[index],
            xyxy=self.xyxy[index],
            confidence=self.confidence[index],
            class_id=self.class_id[index],
        )


def camera_index(camera_ids: Sequence[str]) -> dict[str, int]:
    """Map camera names to their indices, refusing duplicates."""
    names = [str(name) for name in camera_ids]
    if not names:
        raise MatcherError("a matcher needs at least one camera id.")
    if len(set(names)) != len(names):
        raise MatcherError(f"camera ids must be distinct, got {names}.")
    return {name: index for index, name in enumerate(names)}


def decode_messages(
    planes: PlaneSet, cameras: dict[str, int], messages: Sequence[CameraMessage]
) -> Observations:
    """Decode every message's colours at once; detections without a location are dropped.

    Raises:
        MatcherError: a message comes from a camera the matcher was not configured with.
    """
    for message in messages:
        if message.camera_id not in cameras:
            raise MatcherError(
                f"message from unknown camera {message.camera_id!r}; "
                f"known: {', '.join(cameras)}."
            )
    if not messages:
        return Observations(
            np.zeros((0, 2)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64),
            np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64),
        )
    colour = np.concatenate([message.colour for message in messages])
    camera = np.repeat(
        np.array([cameras[message.camera_id] for message in messages], np.int64),
        [len(message) for message in messages],
    )
    world_xy, valid, _ = planes.decode(colour)
    observations = Observations(
        world_xy=world_xy,
        colour=colour,
        camera=camera,
        xyxy=np.concatenate([message.xyxy for message in messages]),
        confidence=np.concatenate([message.confidence for message in messages]),
        class_id=np.concatenate([message.class_id for message in messages]),
    )
    # (Usually every detection is located: then the fresh concatenated columns as they are.)
    return observations if valid.all() else observations[valid]


def instant_frame(messages: Sequence[CameraMessage]) -> int:
    """The frame number reported for an instant: the newest frame among its messages."""
    return max(int(message.frame) for message in messages)


ConfigT = TypeVar("ConfigT")


def build_config(config_type: type[ConfigT], options: dict[str, Any], matcher: str) -> ConfigT:
    """Instantiate an options dataclass, turning unknown names into a clear error."""
    known = {field.name for field in dataclasses.fields(config_type)}  # type: ignore[arg-type]
    unknown = sorted(set(options) - known)
    if unknown:
        raise MatcherError(
            f"unknown option(s) for the {matcher} matcher: {', '.join(unknown)}; "
            f"known: {', '.join(sorted(known))}."
        )
    return config_type(**options)


def require(condition: bool, message: str) -> None:
    """Raise :class:`MatcherError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise MatcherError(message)
