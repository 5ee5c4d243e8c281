"""Clicked points: pixels <-> ground positions, from rows or a CSV file (``u,v,x,y[,name]``)."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.errors import CalibrationError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Correspondences:
    """Clicked points: pixels and the ground positions they show.

    Attributes:
        image_xy: (N, 2) float64 pixel coordinates (raw frame, x right, y down).
        world_xy: (N, 2) float64 ground positions, metres (plane z = 0).
        names: (N,) labels used in messages ("row 3" when the file has none).
        source: where they came from (a file name), for messages.
    """

    image_xy: FloatArray
    world_xy: FloatArray
    names: tuple[str, ...] = ()
    source: str = "points"

    def __post_init__(self) -> None:
        image = np.asarray(self.image_xy, dtype=np.float64)
        world = np.asarray(self.world_xy, dtype=np.float64)
        for array, what in ((image, "image points"), (world, "world points")):
            if array.ndim != 2 or array.shape[1] != 2:
                raise CalibrationError(
                    f"{self.source}: {what} must have shape (N, 2), got {array.shape}."
                )
        if len(image) != len(world):
            raise CalibrationError(
                f"{self.source}: {len(image)} image points but {len(world)} world points."
            )
        names = tuple(self.names) or tuple(f"row {index + 1}" for index in range(len(image)))
        if len(names) != len(image):
            raise CalibrationError(f"{self.source}: {len(names)} names for {len(image)} points.")
        for array, what in ((image, "u, v"), (world, "x, y")):
            bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
            if len(bad):
                raise CalibrationError(
                    f"{self.source}: {names[bad[0]]}: {what} must be finite numbers "
                    "(a point at infinity cannot be clicked)."
                )
        image.setflags(write=False)
        world.setflags(write=False)
        object.__setattr__(self, "image_xy", image)
        object.__setattr__(self, "world_xy", world)
        object.__setattr__(self, "names", names)

    def __len__(self) -> int:
        return len(self.image_xy)

    @classmethod
    def from_rows(
        cls,
        rows: Sequence[Any],
        source: str = "points",
        world_transform: Callable[[FloatArray], FloatArray] | None = None,
    ) -> Correspondences:
        """From rows ``[u, v, x, y]`` or ``[u, v, x, y, name]`` or mappings with those keys.

        Args:
            rows: the rows.
            source: name for messages.
            world_transform: maps (N, 2) given world coordinates to metres (e.g. site-map
                pixels to metres); None when they are metres already.
        """
        image, world, names = [], [], []
        for index, row in enumerate(rows):
            where = f"{source}: row {index + 1}"
            if isinstance(row, dict):
                unknown = sorted(set(row) - {"u", "v", "x", "y", "name"})
                if unknown:
                    raise CalibrationError(
                        f"{where}: unknown key {unknown[0]!r} (u, v, x, y, name)."
                    )
                missing = [key for key in ("u", "v", "x", "y") if key not in row]
                if missing:
                    raise CalibrationError(f"{where}: missing {', '.join(missing)}.")
                values = [row["u"], row["v"], row["x"], row["y"]]
                name = row.get("name")
            else:
                if isinstance(row, str) or not isinstance(row, Sequence) or len(row) not in (4, 5):
                    raise CalibrationError(f"{where}: expected u, v, x, y[, name].")
                values, name = list(row[:4]), (row[4] if len(row) == 5 else None)
            try:
                numbers = [float(value) for value in values]
            except (TypeError, ValueError):
                raise CalibrationError(
                    f"{where}: u, v, x, y must be numbers, got {values}."
                ) from None
            image.append(numbers[:2])
            world.append(numbers[2:])
            names.append(str(name) if name not in (None, "") else f"row {index + 1}")
        world_array = np.array(world, dtype=np.float64).reshape(-1, 2)
        if world_transform is not None and len(world_array):
            world_array = world_transform(world_array)
        return cls(
            np.array(image, dtype=np.float64).reshape(-1, 2), world_array, tuple(names), source
        )

    @classmethod
    def from_csv(
        cls,
        path: str | Path,
        world_transform: Callable[[FloatArray], FloatArray] | None = None,
    ) -> Correspondences:
        """Read a CSV of ``u,v,x,y[,name]`` rows (a header line naming the columns is optional).

        With a header the columns may come in any order; lines starting with ``#`` are comments.
        """
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise CalibrationError(f"points file {path} does not exist.") from None
        except (OSError, UnicodeDecodeError) as error:
            raise CalibrationError(f"cannot read points file {path}: {error}.") from None
        return cls.from_csv_text(text, str(path.name), world_transform)

    @classmethod
    def from_csv_text(
        cls,
        text: str,
        source: str = "points.csv",
        world_transform: Callable[[FloatArray], FloatArray] | None = None,
    ) -> Correspondences:
        lines = [
            line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")
        ]
        records = list(csv.reader(io.StringIO("\n".join(lines))))
        if not records:
            return cls.from_rows([], source, world_transform)
        header = [cell.strip().lower() for cell in records[0]]
        if {"u", "v", "x", "y"} <= set(header):
            unknown = sorted(set(header) - {"u", "v", "x", "y", "name"})
            if unknown:
                raise CalibrationError(
                    f"{source}: unknown column {unknown[0]!r} (columns: u, v, x, y, name)."
                )
            rows: list[Any] = [
                {key: cell.strip() for key, cell in zip(header, record, strict=False)}
                for record in records[1:]
            ]
            for index, (row, record) in enumerate(zip(rows, records[1:], strict=True)):
                if len(record) != len(header):
                    raise CalibrationError(
                        f"{source}: row {index + 1} has {len(record)} values for "
                        f"{len(header)} columns."
                    )
                if not row.get("name"):
                    row.pop("name", None)
        else:
            rows = [[cell.strip() for cell in record] for record in records]
        return cls.from_rows(rows, source, world_transform)

    def to_rows(self) -> list[dict[str, Any]]:
        """``[{"name", "u", "v", "x", "y"}, ...]`` (metres)."""
        return [
            {"name": name, "u": float(u), "v": float(v), "x": float(x), "y": float(y)}
            for name, (u, v), (x, y) in zip(self.names, self.image_xy, self.world_xy, strict=True)
        ]
