"""Pictures: each takes data (and an optional matplotlib Axes where it plots) and returns the
figure or the image.

* reference images made visible and their metric grid (:mod:`cblrs.viz.reference`);
* overlays of boxes, targets, track ids and the grid on camera frames
  (:mod:`cblrs.viz.overlay`);
* bird's-eye trajectories, paper | fusion | ground truth (:mod:`cblrs.viz.trajectories`);
* analytics: places, counts over time, dwell, heatmap, origin-destination
  (:mod:`cblrs.viz.analytics`);
* a calibration from clicked points checked on its image (:mod:`cblrs.viz.calibration`).
"""

from __future__ import annotations

from cblrs.viz.analytics import (
    draw_places,
    plot_counts_over_time,
    plot_dwell,
    plot_heatmap,
    plot_od,
    plot_site,
)
from cblrs.viz.calibration import calibration_picture
from cblrs.viz.overlay import camera_overlay, draw_boxes_3d, id_colour, save_image, world_frame
from cblrs.viz.reference import (
    colourise_reference,
    draw_metric_grid,
    reference_overlay,
    reference_world_map,
)
from cblrs.viz.trajectories import camera_footprint, data_extent, plot_trajectories

__all__ = [
    "calibration_picture",
    "camera_footprint",
    "camera_overlay",
    "colourise_reference",
    "data_extent",
    "draw_boxes_3d",
    "draw_metric_grid",
    "draw_places",
    "id_colour",
    "plot_counts_over_time",
    "plot_dwell",
    "plot_heatmap",
    "plot_od",
    "plot_site",
    "plot_trajectories",
    "reference_overlay",
    "reference_world_map",
    "save_image",
    "world_frame",
]
