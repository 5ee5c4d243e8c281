"""Colour <-> world encoding of a virtual ground plane (the paper's section III-A).

A plane is a rectangle ``[x0, x0 + width] x [y0, y0 + length]`` (metres) at height ``z``.
Its colour code is::

    R = round((x - x0) / step_x)     step_x = width  / (2**bits - 1)
    G = round((y - y0) / step_y)     step_y = length / (2**bits - 1)
    B = plane_id                     (B = 0 is reserved for "no location")

so a colour decodes to the centre of its cell, never more than half a step from the true
point. With 8 bits a 50 m plane has a 19.6 cm step; with 16 bits, 0.76 mm.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from cblrs.errors import PlaneError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SUPPORTED_BITS = (8, 16)
NO_LOCATION = 0


@dataclass(frozen=True)
class PlaneSpec:
    """One colour-coded plane.

    Attributes:
        plane_id: value of the blue channel, 1 .. 2**bits - 1.
        origin: (x0, y0) world corner of the plane, metres.
        width: extent along world x, metres (encoded in R).
        length: extent along world y, metres (encoded in G).
        bits: bits per channel, 8 or 16.
        height: plane height z in metres (0 for the ground).
        name: optional human-readable label.
    """

    plane_id: int
    origin: tuple[float, float]
    width: float
    length: float
    bits: int = 16
    height: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        if self.bits not in SUPPORTED_BITS:
            raise PlaneError(f"bits per channel must be 8 or 16, got {self.bits}.")
        if not 1 <= int(self.plane_id) <= self.max_value:
            raise PlaneError(
                f"plane id must be 1..{self.max_value} for {self.bits}-bit colour "
                f"(0 means no location), got {self.plane_id}."
            )
        values = (*self.origin, self.width, self.length, self.height)
        if len(self.origin) != 2 or not all(np.isfinite(v) for v in values):
            raise PlaneError(f"plane {self.plane_id}: origin, size and height must be finite.")
        if self.width <= 0 or self.length <= 0:
            raise PlaneError(
                f"plane {self.plane_id}: width and length must be positive, "
                f"got {self.width} x {self.length} m."
            )
        object.__setattr__(self, "plane_id", int(self.plane_id))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @property
    def max_value(self) -> int:
        """The largest channel value: 255 (8 bits) or 65535 (16 bits)."""
        return (1 << self.bits) - 1

    @property
    def step(self) -> tuple[float, float]:
        """Quantisation step (x, y) in metres."""
        return self.width / self.max_value, self.length / self.max_value

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        """The image dtype of this bit depth: uint8 or uint16."""
        return np.uint8 if self.bits == 8 else np.uint16

    def contains(self, world_xy: NDArray) -> BoolArray:
        """True for points on the plane rectangle (edges included)."""
        world_xy = _points(world_xy)
        x0, y0 = self.origin
        with np.errstate(invalid="ignore"):
            return (
                (world_xy[:, 0] >= x0)
                & (world_xy[:, 0] <= x0 + self.width)
                & (world_xy[:, 1] >= y0)
                & (world_xy[:, 1] <= y0 + self.length)
            )

    def encode(self, world_xy: NDArray) -> tuple[NDArray[np.uint16], BoolArray]:
        """Colours of world points.

        Args:
            world_xy: (N, 2) metres.

        Returns:
            ``(colours, valid)``: (N, 3) uint16 RGB values (in this plane's bit depth) and
            (N,) bool; points off the plane get ``(0, 0, 0)`` and ``valid = False``.
        """
        world_xy = _points(world_xy)
        valid = self.contains(world_xy)
        colours = np.zeros((len(world_xy), 3), dtype=np.uint16)
        step_x, step_y = self.step
        x0, y0 = self.origin
        colours[valid, 0] = np.rint((world_xy[valid, 0] - x0) / step_x)
        colours[valid, 1] = np.rint((world_xy[valid, 1] - y0) / step_y)
        colours[valid, 2] = self.plane_id
        return colours, valid

    def decode(self, colours: NDArray) -> tuple[FloatArray, BoolArray]:
        """World points (cell centres) of colours; only colours with B == plane_id are valid.

        Args:
            colours: (N, 3) integer RGB values in this plane's bit depth.

        Returns:
            ``(world_xy, valid)``: (N, 2) metres (NaN where invalid) and (N,) bool.
        """
        colours = _colours(colours)
        valid = self._valid(colours)
        world_xy = np.full((len(colours), 2), np.nan)
        world_xy[valid, 0], world_xy[valid, 1] = self._cells_of(colours, valid)
        return world_xy, valid

    def decode_valid(self, colours: NDArray) -> FloatArray:
        """The world points of the colours that are this plane's, in order: what
        ``world_xy[valid]`` of :meth:`decode` holds, without the (N, 2) array of every colour
        (a reference image's sampled colours are some 130,000).

        Args:
            colours: (N, 3) integer RGB values in this plane's bit depth.

        Returns:
            (M, 2) metres, M the number of valid colours.
        """
        colours = _colours(colours)
        valid = self._valid(colours)
        world_xy = np.empty((int(np.count_nonzero(valid)), 2))
        world_xy[:, 0], world_xy[:, 1] = self._cells_of(colours, valid)
        return world_xy

    def _valid(self, colours: NDArray[np.integer]) -> BoolArray:
        return ((colours[:, 2] == self.plane_id) & (colours[:, 0] <= self.max_value)
                & (colours[:, 1] <= self.max_value))

    def _cells_of(self, colours: NDArray[np.integer], valid: BoolArray
                  ) -> tuple[FloatArray, FloatArray]:
        """x and y of the valid colours' cell centres: origin + colour * step, each column
        gathered on its own (a gather of (N, 2) rows, or arithmetic mixing the colours'
        integers with floats in 2-D, costs several times more)."""
        step_x, step_y = self.step
        return (self.origin[0] + colours[:, 0][valid] * step_x,
                self.origin[1] + colours[:, 1][valid] * step_y)

    def to_dict(self) -> dict:
        """JSON-ready fields (the inverse of :meth:`from_dict`)."""
        data = asdict(self)
        data["origin"] = list(self.origin)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> PlaneSpec:
        """A plane from :meth:`to_dict` data; PlaneError for a missing or bad field."""
        known = {"plane_id", "origin", "width", "length", "bits", "height", "name"}
        unknown = set(data) - known
        if unknown:
            raise PlaneError(f"unknown plane field(s): {', '.join(sorted(unknown))}.")
        try:
            return cls(
                plane_id=int(data["plane_id"]),
                origin=(float(data["origin"][0]), float(data["origin"][1])),
                width=float(data["width"]),
                length=float(data["length"]),
                bits=int(data.get("bits", 16)),
                height=float(data.get("height", 0.0)),
                name=str(data.get("name", "")),
            )
        except (KeyError, TypeError, ValueError, IndexError) as error:
            raise PlaneError(f"invalid plane specification {data!r}: {error}.") from None

    @classmethod
    def around(
        cls,
        points_xy: NDArray,
        margin: float = 1.0,
        plane_id: int = 1,
        bits: int = 16,
        height: float = 0.0,
    ) -> PlaneSpec:
        """The smallest plane holding ``points_xy`` (N, 2) plus a margin in metres."""
        points_xy = _points(points_xy)
        points_xy = points_xy[np.isfinite(points_xy).all(axis=1)]
        if len(points_xy) == 0:
            raise PlaneError("cannot size a plane around zero points.")
        low = points_xy.min(axis=0) - margin
        high = points_xy.max(axis=0) + margin
        return cls(plane_id, (low[0], low[1]), high[0] - low[0], high[1] - low[1], bits, height)


class PlaneSet(Sequence[PlaneSpec]):
    """Several planes of one world, all with the same bit depth and distinct ids."""

    def __init__(self, planes: Iterable[PlaneSpec]):
        self._planes = tuple(planes)
        if not self._planes:
            raise PlaneError("at least one plane is needed.")
        ids = [plane.plane_id for plane in self._planes]
        if len(set(ids)) != len(ids):
            raise PlaneError(f"plane ids must be distinct, got {ids}.")
        bits = {plane.bits for plane in self._planes}
        if len(bits) != 1:
            raise PlaneError(
                f"all planes of one image need the same bit depth, got {sorted(bits)}."
            )
        self.bits: int = bits.pop()
        self._by_id = {plane.plane_id: plane for plane in self._planes}

    def __len__(self) -> int:
        return len(self._planes)

    def __getitem__(self, index):
        return self._planes[index]

    def __iter__(self) -> Iterator[PlaneSpec]:
        return iter(self._planes)

    def __repr__(self) -> str:
        return f"PlaneSet({list(self._planes)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, PlaneSet) and self._planes == other._planes

    def __hash__(self) -> int:
        return hash(self._planes)

    def by_id(self, plane_id: int) -> PlaneSpec:
        """The plane with this id; PlaneError naming the known ids otherwise."""
        try:
            return self._by_id[int(plane_id)]
        except KeyError:
            raise PlaneError(
                f"no plane with id {plane_id}; known ids: {sorted(self._by_id)}."
            ) from None

    @property
    def ids(self) -> list[int]:
        """The planes' ids, in order."""
        return [plane.plane_id for plane in self._planes]

    def decode(self, colours: NDArray) -> tuple[FloatArray, BoolArray, NDArray[np.int64]]:
        """Decode colours of any of these planes.

        Returns:
            ``(world_xy, valid, plane_id)``: (N, 2) metres, (N,) bool and (N,) plane ids
            (0 where invalid).
        """
        colours = _colours(colours)
        if len(self._planes) == 1:  # (the same arrays, without merging planes)
            plane = self._planes[0]
            world_xy, valid = plane.decode(colours)
            return world_xy, valid, np.where(valid, plane.plane_id, 0)
        world_xy = np.full((len(colours), 2), np.nan)
        valid = np.zeros(len(colours), dtype=bool)
        plane_ids = np.zeros(len(colours), dtype=np.int64)
        for plane in self._planes:
            plane_xy, plane_valid = plane.decode(colours)
            world_xy[plane_valid] = plane_xy[plane_valid]
            valid |= plane_valid
            plane_ids[plane_valid] = plane.plane_id
        return world_xy, valid, plane_ids

    def to_list(self) -> list[dict]:
        """JSON-ready list of the planes (the inverse of :meth:`from_list`)."""
        return [plane.to_dict() for plane in self._planes]

    @classmethod
    def from_list(cls, items: list[dict]) -> PlaneSet:
        """Planes from :meth:`to_list` data."""
        if not isinstance(items, list):
            raise PlaneError("plane specifications must be a list.")
        return cls(PlaneSpec.from_dict(item) for item in items)


def _points(world_xy: NDArray) -> FloatArray:
    array = np.asarray(world_xy, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"world_xy must have shape (N, 2), got {array.shape}")
    return array


def _colours(colours: NDArray) -> NDArray[np.integer]:
    array = np.asarray(colours)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"colours must have shape (N, 3), got {array.shape}")
    if not np.issubdtype(array.dtype, np.integer):
        if not np.all(np.isfinite(array)) or np.any(array != np.round(array)):
            raise ValueError("colours must be whole numbers")
    # Read only (decoding compares and scales them): unsigned colours, a reference image's,
    # are used as they are, other integers as int64 without a copy when they are already.
    if np.issubdtype(array.dtype, np.unsignedinteger):
        return array
    array = array.astype(np.int64, copy=False)
    if np.any(array < 0):
        raise ValueError("colours must not be negative")
    return array
