"""Pictures: reference images made visible, metric grids, overlays on camera frames."""

from __future__ import annotations

from cblrs.viz.reference import (
    colourise_reference,
    draw_metric_grid,
    reference_overlay,
    reference_world_map,
)

__all__ = [
    "colourise_reference",
    "draw_metric_grid",
    "reference_overlay",
    "reference_world_map",
]
