"""Bird's-eye trajectory plots: predicted tracks against ground truth (the paper's Fig. 6).

Functions take data and an optional matplotlib Axes and return the Figure; they never show
a window (the Agg backend is used when no Axes is given).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.detections import Tracks
from cblrs.viz.overlay import id_colour

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

FloatArray = NDArray[np.float64]

GROUND_TRUTH_COLOUR = "0.55"
CAMERA_COLOUR = "0.15"


def _figure(
    panels: int, area: tuple[float, float, float, float], panel_width: float = 5.2
) -> tuple[Figure, list[Axes]]:
    # A Figure without pyplot: no global state, no GUI backend, safe in threads and tests.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    aspect = (area[3] - area[1]) / max(area[2] - area[0], 1e-9)
    panel_height = float(np.clip(panel_width * aspect, 2.5, 2.0 * panel_width))
    figure = Figure(figsize=(panel_width * panels + 0.4, panel_height + 1.25), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, panels, squeeze=False)[0]
    return figure, list(axes)


def _segments(tracks: Tracks, identity: int, max_gap_s: float) -> list[FloatArray]:
    """The (K, 2) pieces of one identity's path, split where it was not seen for a while."""
    rows = tracks.track_id == identity
    order = np.argsort(tracks.timestamp[rows], kind="stable")
    times = tracks.timestamp[rows][order]
    points = tracks.world_xy[rows][order]
    finite = np.isfinite(points).all(axis=1)
    times, points = times[finite], points[finite]
    if len(points) == 0:
        return []
    breaks = np.flatnonzero(np.diff(times) > max_gap_s) + 1
    return [piece for piece in np.split(points, breaks) if len(piece)]


def _max_gap(tracks: Tracks) -> float:
    times = np.unique(tracks.timestamp)
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    return max(3.0 * step, 1.0)


def data_extent(*tracks: Tracks, margin: float = 1.5) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) around every finite position, metres."""
    points = [t.world_xy[np.isfinite(t.world_xy).all(axis=1)] for t in tracks if len(t)]
    points = [p for p in points if len(p)]
    if not points:
        return (-1.0, -1.0, 1.0, 1.0)
    stacked = np.concatenate(points)
    low = stacked.min(axis=0) - margin
    high = stacked.max(axis=0) + margin
    return (float(low[0]), float(low[1]), float(high[0]), float(high[1]))


def camera_footprint(
    camera: Camera, area: tuple[float, float, float, float], resolution: int = 240
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Where on the ground (inside ``area``) a camera sees, as a boolean raster.

    Returns:
        ``(grid_x, grid_y, seen)``: two (R, R) coordinate grids in metres and the (R, R)
        mask of ground points that project inside the image.
    """
    x_min, y_min, x_max, y_max = area
    grid_x, grid_y = np.meshgrid(
        np.linspace(x_min, x_max, resolution), np.linspace(y_min, y_max, resolution)
    )
    pixels, valid = camera.world_to_pixel(np.column_stack([grid_x.ravel(), grid_y.ravel()]))
    seen = valid & camera.contains(np.nan_to_num(pixels, nan=-1e9))
    return grid_x, grid_y, seen.reshape(grid_x.shape)


def _draw_cameras(
    ax: Axes, cameras: Sequence[Camera], area: tuple[float, float, float, float]
) -> None:
    for index, camera in enumerate(cameras):
        colour = id_colour(index + 3)
        colour_float = tuple(channel / 255 for channel in colour)
        grid_x, grid_y, seen = camera_footprint(camera, area)
        if seen.any() and not seen.all() and len(cameras) <= 2:
            ax.contourf(
                grid_x,
                grid_y,
                seen.astype(float),
                levels=[0.5, 1.5],
                colors=[colour_float],
                alpha=0.07,
                zorder=0,
            )
        if seen.any() and not seen.all():
            ax.contour(
                grid_x,
                grid_y,
                seen.astype(float),
                levels=[0.5],
                colors=[colour_float],
                linewidths=0.9 if len(cameras) <= 2 else 0.7,
                alpha=0.6 if len(cameras) <= 2 else 0.45,
                zorder=0,
            )
        elif seen.all() and len(cameras) <= 2:
            ax.add_patch(_rectangle(area, colour_float))
        if camera.has_pose:
            centre = camera.centre
            ax.plot(
                centre[0],
                centre[1],
                marker="^",
                markersize=9,
                color=colour_float,
                markeredgecolor=CAMERA_COLOUR,
                linestyle="none",
                zorder=5,
            )
            ax.annotate(
                camera.name,
                (centre[0], centre[1]),
                textcoords="offset points",
                xytext=(6, 6),
                fontsize=8,
                color=CAMERA_COLOUR,
                zorder=5,
            )


def _draw_markings(ax: Axes, markings: Sequence[Any]) -> None:
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.patches import Polygon

    for marking in markings:
        colour = tuple(channel / 255 for channel in marking.colour)
        polygon = np.asarray(marking.polygon, dtype=np.float64).reshape(-1, 2)
        ax.add_patch(
            Polygon(polygon, closed=True, facecolor=colour, edgecolor="none", alpha=0.35, zorder=-1)
        )


def _rectangle(area: tuple[float, float, float, float], colour: tuple[float, ...]):
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.patches import Rectangle

    x_min, y_min, x_max, y_max = area
    return Rectangle((x_min, y_min), x_max - x_min, y_max - y_min, color=colour, alpha=0.05)


def _draw_tracks(ax: Axes, tracks: Tracks, coloured: bool, line_width: float) -> None:
    max_gap = _max_gap(tracks)
    for identity in np.unique(tracks.track_id):
        pieces = _segments(tracks, int(identity), max_gap)
        colour: tuple[float, ...] | str = GROUND_TRUTH_COLOUR
        style = "--"
        if coloured:
            colour = tuple(channel / 255 for channel in id_colour(int(identity)))
            style = "-"
        for piece in pieces:
            ax.plot(
                piece[:, 0],
                piece[:, 1],
                style,
                color=colour,
                linewidth=line_width,
                alpha=0.95 if coloured else 0.8,
                zorder=2 if coloured else 1,
            )
        if coloured and pieces:
            start, end = pieces[0][0], pieces[-1][-1]
            ax.plot(
                *start,
                marker="o",
                markersize=4.5,
                color=colour,
                markeredgecolor="k",
                markeredgewidth=0.5,
                linestyle="none",
                zorder=3,
            )
            ax.plot(
                *end,
                marker="s",
                markersize=4.5,
                color=colour,
                markeredgecolor="k",
                markeredgewidth=0.5,
                linestyle="none",
                zorder=3,
            )


def _legend_handles(show_ground_truth: bool, show_cameras: bool) -> list:
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.lines import Line2D

    handles = []
    if show_ground_truth:
        handles.append(
            Line2D(
                [],
                [],
                color=GROUND_TRUTH_COLOUR,
                linestyle="--",
                linewidth=1.2,
                label="ground truth",
            )
        )
    handles += [
        Line2D([], [], color="tab:blue", linewidth=1.8, label="track (colour = id)"),
        Line2D(
            [],
            [],
            marker="o",
            color="0.3",
            markeredgecolor="k",
            linestyle="none",
            markersize=5,
            label="start",
        ),
        Line2D(
            [],
            [],
            marker="s",
            color="0.3",
            markeredgecolor="k",
            linestyle="none",
            markersize=5,
            label="end",
        ),
    ]
    if show_cameras:
        handles.append(
            Line2D(
                [],
                [],
                marker="^",
                color="0.6",
                markeredgecolor=CAMERA_COLOUR,
                linestyle="none",
                markersize=8,
                label="camera, its view outlined",
            )
        )
    return handles


def _panel(
    ax: Axes,
    title: str,
    tracks: Tracks,
    ground_truth: Tracks | None,
    cameras: Sequence[Camera] | None,
    area: tuple[float, float, float, float],
) -> None:
    if cameras:
        _draw_cameras(ax, cameras, area)
    if ground_truth is not None and len(ground_truth):
        _draw_tracks(ax, ground_truth, coloured=False, line_width=1.0)
    _draw_tracks(ax, tracks, coloured=True, line_width=1.6)
    identities = len(np.unique(tracks.track_id))
    ax.set_title(f"{title}  ({identities} ids)", fontsize=11)
    ax.set_xlim(area[0], area[2])
    ax.set_ylim(area[1], area[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, linewidth=0.4, alpha=0.4)


def plot_trajectories(
    ground_truth: Tracks,
    predictions: Tracks | Mapping[str, Tracks],
    ax: Axes | Sequence[Axes] | None = None,
    title: str | None = None,
    cameras: Sequence[Camera] | None = None,
    area: tuple[float, float, float, float] | None = None,
    markings: Sequence[Any] = (),
) -> Figure:
    """Bird's-eye view of predicted trajectories against the ground truth.

    With one set of predictions: one panel, ground truth as grey dashed lines, predictions
    coloured by track id with start (circle) and end (square) markers. With several named
    sets (e.g. ``{"paper": ..., "fusion": ...}``): one panel per set plus a ground-truth
    panel coloured by true id, side by side as in the paper's Fig. 6.

    Args:
        ground_truth: true positions (``track_id`` = object identity), metres.
        predictions: predicted tracks, or a mapping name -> tracks.
        ax: an Axes for one panel, or one Axes per panel; None makes a new Figure.
        title: figure title (single panel: the panel title).
        cameras: cameras whose positions and ground footprints to draw.
        area: (x_min, y_min, x_max, y_max) in metres; default: around all positions.
        markings: background polygons, objects with ``polygon`` ((x, y), ... metres) and
            ``colour`` (r, g, b), e.g. roads of a synthetic world.

    Returns:
        The matplotlib Figure.

    Example:
        >>> import numpy as np
        >>> truth = Tracks(np.arange(3), np.arange(3.0), np.zeros(3, int), np.c_[0:3, 0:3])
        >>> figure = plot_trajectories(truth, {"fusion": truth})
        >>> len(figure.axes)
        2
    """
    if isinstance(predictions, Tracks):
        named: dict[str, Tracks] = {title or "predicted": predictions}
        single = True
    else:
        named = dict(predictions)
        if not named:
            raise ValueError("predictions must hold at least one set of tracks")
        single = False
    if area is None:
        area = data_extent(ground_truth, *named.values())
    panels = 1 if single else len(named) + 1
    if ax is None:
        figure, axes = _figure(panels, area)
    else:
        axes = [ax] if not isinstance(ax, Sequence) else list(ax)
        if len(axes) != panels:
            raise ValueError(f"{panels} panel(s) to draw but {len(axes)} Axes given")
        figure = axes[0].figure  # type: ignore[assignment]
    for axis in axes:
        _draw_markings(axis, markings)
    for axis, (name, tracks) in zip(axes, named.items(), strict=False):
        _panel(axis, name, tracks, ground_truth, cameras, area)
    handles = _legend_handles(len(ground_truth) > 0, bool(cameras))
    if single:
        axes[0].legend(handles=handles, loc="best", fontsize=7.5, framealpha=0.85)
    else:
        _panel(axes[-1], "ground truth", ground_truth, None, cameras, area)
        figure.legend(
            handles=handles,
            loc="outside lower center",
            ncol=len(handles),
            fontsize=8.5,
            frameon=False,
        )
        if title:
            figure.suptitle(title, fontsize=13)
    return figure
