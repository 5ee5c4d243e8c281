"""The paper's matcher (section III-C-2), reimplemented faithfully.

Every object keeps the detections appended to it; its current position is the colour of
its latest detection. For each received message in turn, the Euclidean distance between
every detection's colour and every object's current colour is the cost of a Hungarian
assignment; an assigned pair farther apart than a threshold does not match, and every
unmatched detection creates a new object. Objects are never deleted (the paper mentions no
removal) and have no motion model.

Distance is measured in colour units, as in the paper: the Euclidean distance of the
(R, G, B) values. R and G are cell indices along world x and y, so with a non-square plane
one colour unit is a different length along x and y (WILDTRACK at 16 bits: 0.18 mm along x,
0.55 mm along y). The threshold is given in metres and converted with the geometric mean of
the two steps of the first plane, which is what a reimplementer setting "about a metre"
would do. ``space="metres"`` measures in decoded metres instead (an ablation, not the
paper).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from cblrs.detections import CameraMessage, Tracks
from cblrs.matching.base import (
    MatcherError,
    build_config,
    camera_index,
    decode_messages,
    instant_frame,
    require,
)
from cblrs.matching.solvers import linear_sum_assignment
from cblrs.plane import PlaneSet

STATE_VERSION = "cblrs.paper-matcher/1"


@dataclass(frozen=True)
class PaperConfig:
    """Options of the paper matcher.

    Attributes:
        threshold_m: assignment distance above which a detection starts a new object,
            metres-equivalent (see the module docstring for the conversion).
        space: ``"colour"`` (the paper) or ``"metres"``.
    """

    threshold_m: float = 1.0
    space: str = "colour"

    def __post_init__(self) -> None:
        require(
            isinstance(self.threshold_m, int | float) and math.isfinite(self.threshold_m)
            and self.threshold_m > 0,
            f"threshold_m must be a positive number of metres, got {self.threshold_m!r}.",
        )
        require(
            self.space in ("colour", "metres"),
            f"space must be 'colour' or 'metres', got {self.space!r}.",
        )


class PaperMatcher:
    """Colour-distance Hungarian matcher of the paper.

    Example:
        >>> from cblrs.plane import PlaneSet, PlaneSpec
        >>> matcher = PaperMatcher(PlaneSet([PlaneSpec(1, (0, 0), 10, 10)]), ["a", "b"])
        >>> len(matcher.update(0.0, []))
        0
    """

    name = "paper"

    def __init__(self, planes: PlaneSet, camera_ids: Sequence[str], **options: Any):
        self.config = build_config(PaperConfig, options, self.name)
        self.planes = planes if isinstance(planes, PlaneSet) else PlaneSet(planes)
        self.camera_ids = [str(name) for name in camera_ids]
        self._cameras = camera_index(self.camera_ids)
        step_x, step_y = self.planes[0].step
        self._threshold = (
            self.config.threshold_m / math.sqrt(step_x * step_y)
            if self.config.space == "colour"
            else self.config.threshold_m
        )
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        self._ids = np.zeros(0, np.int64)
        self._colour = np.zeros((0, 3), np.int64)  # latest colour of each object
        self._world_xy = np.zeros((0, 2))  # its decoded position
        self._last_seen = np.zeros(0)
        self._detections = np.zeros(0, np.int64)  # detections appended so far
        self._next_id = 1

    @property
    def object_count(self) -> int:
        """Objects the matcher currently remembers."""
        return len(self._ids)

    def _points(self, colour: np.ndarray, world_xy: np.ndarray) -> np.ndarray:
        return colour.astype(np.float64) if self.config.space == "colour" else world_xy

    def update(self, timestamp: float, messages: Sequence[CameraMessage]) -> Tracks:
        """Match one instant's messages to the objects; their rows (see
        :class:`~cblrs.matching.base.Matcher`)."""
        if not messages:
            return Tracks.empty()
        touched: dict[int, tuple[int, np.ndarray, int]] = {}  # row -> (camera, box, class)
        for message in messages:
            observed = decode_messages(self.planes, self._cameras, [message])
            if len(observed) == 0:
                continue
            detections = self._points(observed.colour, observed.world_xy)
            objects = self._points(self._colour, self._world_xy)
            assigned_object = np.full(len(observed), -1)
            if len(objects):
                cost = np.linalg.norm(detections[:, None, :] - objects[None, :, :], axis=2)
                rows, columns = linear_sum_assignment(cost)
                keep = cost[rows, columns] <= self._threshold
                assigned_object[rows[keep]] = columns[keep]
            new = assigned_object < 0
            if new.any():
                count = int(new.sum())
                assigned_object[new] = len(self._ids) + np.arange(count)
                self._ids = np.concatenate(
                    [self._ids, self._next_id + np.arange(count, dtype=np.int64)]
                )
                self._next_id += count
                self._colour = np.concatenate([self._colour, np.zeros((count, 3), np.int64)])
                self._world_xy = np.concatenate([self._world_xy, np.zeros((count, 2))])
                self._last_seen = np.concatenate([self._last_seen, np.zeros(count)])
                self._detections = np.concatenate([self._detections, np.zeros(count, np.int64)])
            self._colour[assigned_object] = observed.colour
            self._world_xy[assigned_object] = observed.world_xy
            self._last_seen[assigned_object] = timestamp
            self._detections[assigned_object] += 1
            for row, camera, box, class_id in zip(
                assigned_object.tolist(), observed.camera.tolist(), observed.xyxy,
                observed.class_id.tolist(), strict=True,
            ):
                touched[row] = (camera, box, class_id)
        rows = np.array(sorted(touched), dtype=np.int64)
        count = len(rows)
        return Tracks(
            frame=np.full(count, instant_frame(messages)),
            timestamp=np.full(count, float(timestamp)),
            track_id=self._ids[rows],
            world_xy=self._world_xy[rows].reshape(-1, 2),
            camera_id=np.array([touched[row][0] for row in rows.tolist()], np.int64),
            xyxy=np.array([touched[row][1] for row in rows.tolist()]).reshape(-1, 4),
            class_id=np.array([touched[row][2] for row in rows.tolist()], np.int64),
        )

    def get_state(self) -> dict:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "version": STATE_VERSION,
            "config": asdict(self.config),
            "camera_ids": list(self.camera_ids),
            "next_id": self._next_id,
            "ids": self._ids.tolist(),
            "colour": self._colour.tolist(),
            "world_xy": self._world_xy.tolist(),
            "last_seen": self._last_seen.tolist(),
            "detections": self._detections.tolist(),
        }

    def set_state(self, state: dict) -> None:
        """Restore a state saved by :meth:`get_state`."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise MatcherError(f"not a saved paper-matcher state (expected {STATE_VERSION}).")
        if state.get("camera_ids") != self.camera_ids:
            raise MatcherError(
                f"the saved state is for cameras {state.get('camera_ids')}, "
                f"this matcher has {self.camera_ids}."
            )
        try:
            self._next_id = int(state["next_id"])
            self._ids = np.asarray(state["ids"], np.int64).reshape(-1)
            self._colour = np.asarray(state["colour"], np.int64).reshape(-1, 3)
            self._world_xy = np.asarray(state["world_xy"], np.float64).reshape(-1, 2)
            self._last_seen = np.asarray(state["last_seen"], np.float64).reshape(-1)
            self._detections = np.asarray(state["detections"], np.int64).reshape(-1)
        except (KeyError, TypeError, ValueError) as error:
            raise MatcherError(f"the saved paper-matcher state is incomplete: {error}.") from None
