"""Where a vehicle's footprint centre lies, from where its box's target pixel lands.

A camera sends the reference colour at a box's target pixel (:mod:`cblrs.targeting`: for
vehicles the box's centre column, 85 % of the way down from its top). Seen from above, a
car's box bottom is the edge of its footprint nearest the camera and its top the far edge of
its roof, so the ground point under the target pixel lands on the camera's ray, short of the
footprint centre (the ground truth of the AI City protocol) by an amount that depends on the
vehicle's extent along the ray: ``e = |L/2 cos(phi)| + |W/2 sin(phi)|`` for a footprint of
length ``L`` and width ``W`` whose heading makes an angle ``phi`` with the ray. Lying along
the ray a car's near edge is 2.25 m nearer than its centre; across it, 0.9 m.

:class:`Footprint` moves each vehicle detection to the footprint centre that would have put
the target pixel where it is. Image rows measure depth along the camera's *viewing
direction* (learned from its reference image), not along the ray to the car, so the extent
``e`` is taken along that direction: a camera at height ``H`` sees the box bottom (near
ground edge, ``rho - e`` deep) at depression ``atan(H / (rho - e))`` and the box top (far
roof edge, height ``h``) at ``atan((H - h) / (rho + e))``; the target's depression is
between them at the targeting fraction, and its ground point is ``H / tan`` of it (angles
stand in for image rows: the box spans a few degrees, where they are proportional). Image
columns are ``side / depth``: seen obliquely, a car's near end spreads wider than its far
end, so the box's centre column is not the centre's, and the detection moves across too.
Before association the heading is unknown and the shift is its average over headings; once
a detection is given a track whose heading is known, the shift is that heading's. Only
classes with a size below (vehicles) move; people keep their foot point, and cameras whose
height is unknown are left alone. Only the matcher changes: cameras still send one colour
per box.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cblrs.detections import CLASS_NAMES, CLASS_SIZE_PRIORS
from cblrs.matching.base import Observations
from cblrs.matching.fusion.table import Measured, TrackTable
from cblrs.targeting import targeting_for

VEHICLE_SIZES: dict[str, tuple[float, float, float]] = {
    name: size for name, size in CLASS_SIZE_PRIORS.items() if name != "person"
}
"""Length, width, height (metres) of the classes this stage moves: every class of
:data:`cblrs.detections.CLASS_SIZE_PRIORS` but people, who keep their foot point."""

_HEADING_SAMPLES = 16  # headings over a quarter turn averaged while the heading is unknown
_ITERATIONS = 3  # fixed-point steps from the located point back to the footprint centre


def target_offset(
    distance: np.ndarray,
    camera_height: np.ndarray,
    extent: np.ndarray,
    height: np.ndarray,
    fraction: np.ndarray,
) -> np.ndarray:
    """(N,) metres from the footprint centre to where the target pixel lands, along the ray.

    Negative: the located point is short of the centre (nearer the camera).

    Args:
        distance: (N,) ground distance from the camera to the footprint centre, metres.
        camera_height: (N,) metres above the ground.
        extent: (N,) the footprint's half extent along the ray, metres.
        height: (N,) the vehicle's height, metres.
        fraction: (N,) the target's fraction of the box height from its top.
    """
    near = np.maximum(distance - extent, 1e-3)
    bottom = np.arctan(camera_height / near)
    top = np.arctan((camera_height - height) / (distance + extent))
    target = top + fraction * (bottom - top)
    return camera_height / np.tan(target) - distance


def half_extent(
    length: np.ndarray, width: np.ndarray, cosine: np.ndarray, sine: np.ndarray
) -> np.ndarray:
    """(N,) half the footprint's extent along a ray at ``(cosine, sine)`` to its heading."""
    return np.abs(0.5 * length * cosine) + np.abs(0.5 * width * sine)


class Footprint:
    """Moves vehicle detections along their rays to their footprint centres.

    Args:
        camera_ids: the tracker's cameras, in its order.
        camera_positions: ``{camera: (x, y, height)}`` metres; cameras without a height are
            not corrected.
        sizes: class name -> (length, width, height) metres; other classes are not corrected.

    Example:
        >>> footprint = Footprint(["a"], {"a": (0.0, 0.0, 10.0)})
        >>> car = np.array([CLASS_NAMES.index("car")])
        >>> ray = np.array([[1.0, 0.0]])
        >>> footprint.shift(np.array([25.0]), ray, np.array([0]), car).round(2)
        array([[0.96, 0.  ]])
    """

    def __init__(
        self,
        camera_ids: Sequence[str],
        camera_positions: Mapping[str, Sequence[float]] | None,
        sizes: Mapping[str, tuple[float, float, float]] = VEHICLE_SIZES,
    ):
        self.camera_xy = np.full((len(camera_ids), 2), np.nan)
        self.camera_height = np.full(len(camera_ids), np.nan)
        for index, name in enumerate(camera_ids):
            position = (camera_positions or {}).get(name)
            if position is not None and len(position) == 3:
                self.camera_xy[index] = position[:2]
                self.camera_height[index] = float(position[2])
        # Each camera's viewing direction on the ground (NaN: unknown, see set_view).
        self.forward = np.full((len(camera_ids), 2), np.nan)
        # Per class slot (CLASS_NAMES plus one for unknown ids): size, targeting fraction.
        self.size = np.full((len(CLASS_NAMES) + 1, 3), np.nan)
        self.fraction = np.ones(len(CLASS_NAMES) + 1)
        for index, name in enumerate(CLASS_NAMES):
            if name in sizes:
                self.size[index] = sizes[name]
                self.fraction[index] = targeting_for(name).vertical
        self.enabled = bool(np.isfinite(self.camera_height).any())

    @classmethod
    def from_config(cls, camera_ids: Sequence[str], config: Any) -> Footprint:
        """The tracker's stage: off unless ``config.vehicle_footprint``
        (:class:`~cblrs.matching.fusion.config.FusionConfig`).

        Step 4d of the tracker: once a detection has a track, :meth:`refine` moves it again
        by that track's heading.
        """
        return cls(camera_ids, config.camera_positions if config.vehicle_footprint else None)

    def set_view(self, camera: int, reference: Any) -> None:
        """Learn a camera's viewing direction on the ground from its reference image.

        An image row is a line on the ground square to the camera's viewing direction (for
        a camera that is not rolled), so what decides which of a car's corners is the box
        bottom is how far each lies *along that direction*, not along the ray to the car:
        seen 15 degrees off the image's centre, a car across the ray has one end nearer than
        the other. The direction is that from the camera to the ground under the image's
        centre column.

        Args:
            camera: the camera's index.
            reference: its :class:`~cblrs.reference.ReferenceImage` or on-demand reference.
        """
        if not np.isfinite(self.camera_height[camera]):
            return
        width, height = reference.image_size
        rows = np.linspace(0.55 * height, height - 1.0, 9)
        pixels = np.column_stack([np.full(len(rows), 0.5 * width), rows])
        colours, inside = reference.colours_at(pixels)
        world_xy, valid, _ = reference.planes.decode(colours[inside])
        if not valid.any():
            return
        offset = np.mean(world_xy[valid], axis=0) - self.camera_xy[camera]
        norm = float(np.hypot(*offset))
        if norm > 0:
            self.forward[camera] = offset / norm

    def applies(self, camera: np.ndarray, class_id: np.ndarray) -> np.ndarray:
        """(N,) bool: detections this corrects (a sized class, a camera of known height,
        lower than the camera)."""
        slot = _slot(class_id)
        height = self.camera_height[camera]
        return np.isfinite(height) & np.isfinite(self.size[slot, 2]) & (height > self.size[slot, 2])

    def shift(
        self,
        distance: np.ndarray,
        direction: np.ndarray,
        camera: np.ndarray,
        class_id: np.ndarray,
        heading: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, 2) metres to move each detection to its footprint centre.

        Along the camera's viewing direction (image rows) by the row model of the module
        docstring; across it (image columns) because the box's centre column is not the
        centre's: seen obliquely, a car's near end spreads wider in the image than its far
        end. Columns are ``side / forward`` of the footprint's corners (the roof's corners
        spread the same to a few per cent and are left out).

        Args:
            distance: (N,) ground distance from the camera to where the target landed.
            direction: (N, 2) unit rays from the camera.
            camera: (N,) camera indices.
            class_id: (N,) class ids.
            heading: (N, 2) unit headings (NaN rows: unknown, averaged over headings);
                None: all unknown.
        """
        count = len(distance)
        shift = np.zeros((count, 2))
        rows = np.flatnonzero(self.applies(camera, class_id)) if count else np.zeros(0, int)
        if not len(rows):
            return shift
        slot = _slot(class_id[rows])
        length, width, height = (column[:, None] for column in self.size[slot].T)
        ray = direction[rows]
        forward = self.forward[camera[rows]]
        forward = np.where(np.isfinite(forward), forward, ray)
        side = np.column_stack([-forward[:, 1], forward[:, 0]])
        located = distance[rows, None] * ray
        # The target in the camera's frame: depth along its viewing direction (rows) and
        # side over depth (columns).
        depth = np.maximum(np.einsum("ij,ij->i", located, forward), 1e-3)[:, None]
        column = (np.einsum("ij,ij->i", located, side) / depth[:, 0])[:, None]
        if heading is None:
            heading = np.full((count, 2), np.nan)
        along = np.einsum("ij,ij->i", heading[rows], forward)
        across = np.einsum("ij,ij->i", heading[rows], side)
        unknown = ~np.isfinite(along)
        # Unknown headings: every heading of a half turn, equally likely.
        angles = (np.arange(_HEADING_SAMPLES) + 0.5) * (np.pi / _HEADING_SAMPLES)
        head_f = np.where(unknown[:, None], np.cos(angles)[None], np.nan_to_num(along)[:, None])
        head_s = np.where(unknown[:, None], np.sin(angles)[None], np.nan_to_num(across)[:, None])
        extent = half_extent(length, width, head_f, head_s)
        # Footprint corners relative to the centre, (K, samples, 4) forward and side.
        signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], np.float64)
        corner_f = (
            signs[:, 0] * (0.5 * length * head_f)[..., None]
            - signs[:, 1] * (0.5 * width * head_s)[..., None]
        )
        corner_s = (
            signs[:, 0] * (0.5 * length * head_s)[..., None]
            + signs[:, 1] * (0.5 * width * head_f)[..., None]
        )
        camera_height = self.camera_height[camera[rows]][:, None]
        fraction = self.fraction[slot][:, None]
        centre_f = np.broadcast_to(depth, extent.shape).copy()
        centre_s = centre_f * column
        for _ in range(_ITERATIONS):
            centre_f = depth - target_offset(centre_f, camera_height, extent, height, fraction)
            corners = (centre_s[..., None] + corner_s) / np.maximum(
                centre_f[..., None] + corner_f, 1e-3
            )
            middle = 0.5 * (corners.max(axis=-1) + corners.min(axis=-1))
            centre_s = centre_f * (column - (middle - centre_s / centre_f))
        move_f = np.mean(centre_f, axis=1) - depth[:, 0]
        move_s = np.mean(centre_s, axis=1) - (depth * column)[:, 0]
        shift[rows] = move_f[:, None] * forward + move_s[:, None] * side
        return shift

    def centre(
        self, observed: Observations, measured: Measured, heading: np.ndarray | None = None
    ) -> Observations:
        """The detections with vehicles at their footprint centres (others unchanged)."""
        if not self.enabled or not len(observed.world_xy):
            return observed
        shift = self.shift(
            measured.distance, measured.direction, observed.camera, observed.class_id, heading
        )
        return dataclasses.replace(observed, world_xy=observed.world_xy + shift)

    def refine(
        self,
        observed: Observations,
        measured: Measured,
        tracks: TrackTable,
        assigned: np.ndarray,
    ) -> Observations:
        """Detections :meth:`centre` moved with the average heading, moved again with the
        heading of the track each was given (where it is known)."""
        if not self.enabled or not len(observed.world_xy):
            return observed
        heading = np.full((len(assigned), 2), np.nan)
        matched = np.flatnonzero(assigned >= 0)
        known = np.isfinite(tracks.heading_time[assigned[matched]]) & (
            np.hypot(*tracks.heading[assigned[matched]].T) > 0
        )
        rows = matched[known]
        if not len(rows):
            return observed
        heading[rows] = tracks.heading[assigned[rows]]
        before = self.shift(
            measured.distance, measured.direction, observed.camera, observed.class_id
        )
        after = self.shift(
            measured.distance, measured.direction, observed.camera, observed.class_id, heading
        )
        moved = observed.world_xy.copy()
        moved[rows] += (after - before)[rows]
        return dataclasses.replace(observed, world_xy=moved)


def _slot(class_id: np.ndarray) -> np.ndarray:
    class_id = np.asarray(class_id, np.int64)
    return np.where((class_id >= 0) & (class_id < len(CLASS_NAMES)), class_id, len(CLASS_NAMES))
