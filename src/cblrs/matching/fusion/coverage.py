"""Where each camera sees the ground, learned from its detections (multi-view confirmation).

A real detector fires on a sign or a reflection frame after frame: one camera sees a
"person" standing there, consistently, and a track built on it looks as solid as a real
one. What gives it away is the other cameras: they see the same ground (they locate people
walking through it) and see nobody. :class:`Coverage` counts, on a grid over the planes,
how many detections each camera has located in each cell; a camera covers a cell once it
has located a few there — or, better, it is told where each camera sees the ground
(:meth:`Coverage.set_view`: the cells its reference image holds, which also covers ground
nobody walks on, where a false positive is as likely as anywhere). A new track is then
confirmed only when two cameras have seen it,
unless fewer than two cameras cover where it is (where one camera alone sees the ground, one
camera must do). Until a camera has seen enough of the ground (a fresh tracker), nothing
is covered and one camera confirms, as before.

The grid is learned online and costs one histogram update per window. What it has learnt
is part of the tracker's saved state (only the cells a camera has located something in,
each count capped at what covering needs), so a restarted matcher confirms exactly as the
undisturbed one would.
"""

from __future__ import annotations

import numpy as np

from cblrs.plane import PlaneSet

_MAX_CELLS = 250_000  # per camera: a finer grid over a very large plane is coarsened
_FEW = 64  # detections counted one by one rather than through np.unique


class Coverage:
    """Per camera, how many detections it located in each cell of a grid over the planes.

    Args:
        planes: the planes; the grid spans their union's bounding rectangle.
        camera_count: C.
        cell_m: grid step, metres (coarsened to at most 250,000 cells per camera).
        covering_count: detections a camera must have located in a cell to cover it.
    """

    def __init__(self, planes: PlaneSet, camera_count: int, cell_m: float = 1.0,
                 covering_count: int = 3):
        low = np.min([plane.origin for plane in planes], axis=0).astype(np.float64)
        high = np.max([(plane.origin[0] + plane.width, plane.origin[1] + plane.length)
                       for plane in planes], axis=0).astype(np.float64)
        extent = np.maximum(high - low, 1e-6)
        cell = max(cell_m, float(np.sqrt(extent[0] * extent[1] / _MAX_CELLS)))
        self.low, self.cell = low, cell
        self.shape = tuple(int(v) for v in np.ceil(extent / cell).astype(int) + 1)
        self.camera_count = camera_count
        self.covering_count = covering_count
        self.counts = np.zeros((camera_count, *self.shape), np.int32)
        self.view = np.zeros((camera_count, *self.shape), dtype=bool)
        self.has_view = np.zeros(camera_count, dtype=bool)

    def reset(self) -> None:
        """Forget everything learnt (the views set by :meth:`set_view` stay)."""
        self.counts[:] = 0

    def set_view(self, camera: int, world_xy: np.ndarray) -> None:
        """Tell which ground a camera sees: (M, 2) metres, points its image locates.

        From then on that camera covers exactly the cells holding these points (what it has
        located no longer matters for it).
        """
        column, row, inside = self._cells(np.asarray(world_xy, np.float64).reshape(-1, 2))
        self.view[camera] = False
        self.view[camera, column[inside], row[inside]] = True
        self.has_view[camera] = True

    def _cells(self, world_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Column by column (the same arithmetic; 2-D reductions over two columns are slow on
        # a reference image's 130,000 points).
        column = np.floor((world_xy[:, 0] - self.low[0]) / self.cell).astype(np.int64)
        row = np.floor((world_xy[:, 1] - self.low[1]) / self.cell).astype(np.int64)
        inside = (column >= 0) & (row >= 0) & (column < self.shape[0]) & (row < self.shape[1])
        return column, row, inside

    def learn(self, world_xy: np.ndarray, camera: np.ndarray) -> None:
        """Count located detections: (N, 2) metres, (N,) camera index."""
        learning = ~self.has_view[camera]  # a camera whose view was told learns nothing
        if not learning.any():
            return
        column, row, inside = self._cells(world_xy[learning])
        flat = np.ravel_multi_index(
            (camera[learning][inside], column[inside], row[inside]), self.counts.shape)
        # Saturating: a cell only needs to reach covering_count.
        if len(flat) <= _FEW:  # (a window's few detections: cheaper than np.unique)
            counts = self.counts.reshape(-1)
            for cell in flat.tolist():
                counts[cell] = min(counts[cell] + 1, self.covering_count)
            return
        cells, added = np.unique(flat, return_counts=True)
        self.counts.flat[cells] = np.minimum(self.counts.flat[cells] + added,
                                             self.covering_count)

    def get_state(self) -> dict:
        """What has been learnt, JSON-ready: the flat indices and counts of the non-empty
        cells (the views told by :meth:`set_view` are configuration, not state)."""
        # Saved with every committed group: with every camera's view told (what `cblrs
        # matcher` and `cblrs track` do) nothing is learnt, so skip the scan of the grid.
        cells = (np.zeros(0, np.int64) if self.has_view.all()
                 else np.flatnonzero(self.counts))
        return {"shape": list(self.counts.shape), "cells": cells.tolist(),
                "counts": self.counts.flat[cells].tolist()}

    def set_state(self, state: dict | None) -> None:
        """Restore :meth:`get_state`'s data; ``None`` (a state saved before coverage was
        kept) starts from nothing learnt."""
        self.reset()
        if state is None:
            return
        if list(state["shape"]) != list(self.counts.shape):
            raise ValueError(f"coverage grid {state['shape']} is not this tracker's "
                             f"{list(self.counts.shape)}")
        cells = np.asarray(state["cells"], np.int64)
        counts = np.asarray(state["counts"], np.int64)
        if cells.shape != counts.shape or (cells.size and (
                cells.min() < 0 or cells.max() >= self.counts.size)):
            raise ValueError("coverage cells out of the grid")
        self.counts.flat[cells] = np.clip(counts, 0, self.covering_count)

    def covering(self, world_xy: np.ndarray) -> np.ndarray:
        """(T,) int64: how many cameras cover each position (0 off the grid)."""
        return self.covered_by(world_xy).sum(axis=0).astype(np.int64)

    def covered_by(self, world_xy: np.ndarray) -> np.ndarray:
        """(C, T) bool: which cameras cover each position (none off the grid)."""
        covered = np.zeros((self.camera_count, len(world_xy)), dtype=bool)
        if len(world_xy) == 0:
            return covered
        column, row, inside = self._cells(world_xy)
        inner = self.counts[:, column[inside], row[inside]] >= self.covering_count
        told = self.has_view
        inner[told] = self.view[told][:, column[inside], row[inside]]
        covered[:, inside] = inner
        return covered
