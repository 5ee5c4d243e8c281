"""Pictures of the analytics: places on the ground, counts over time, dwell, heatmap, OD.

Functions take data and an optional matplotlib Axes and return the Figure; they never show
a window (a Figure with the Agg canvas is made when no Axes is given).
"""

from __future__ import annotations

from collections import defaultdict
from typing import TYPE_CHECKING, Any

import numpy as np

from cblrs.analytics.config import HeatmapGrid, TimeBins
from cblrs.analytics.tables import AnalyticsResult
from cblrs.detections import Tracks
from cblrs.places import Places

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

ZONE_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
LINE_COLOUR = "#d62728"


def _axes(ax: Axes | None, size: tuple[float, float]) -> tuple[Figure, Axes]:
    if ax is not None:
        return ax.figure, ax  # type: ignore[return-value]
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(figure)
    return figure, figure.add_subplot()


def draw_places(ax: Axes, places: Places, labels: bool = True) -> None:
    """Zones as translucent polygons, lines as red segments with an arrow to the positive side."""
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.patches import Polygon

    for index, zone in enumerate(places.zones):
        colour = ZONE_COLOURS[index % len(ZONE_COLOURS)]
        ax.add_patch(Polygon(zone.polygon, closed=True, facecolor=colour, alpha=0.18,
                             edgecolor=colour, linewidth=1.5))
        if labels:
            centre = zone.polygon.mean(axis=0)
            ax.text(centre[0], centre[1], zone.name, color=colour, ha="center", va="center",
                    fontsize=8, weight="bold")
    for line in places.lines:
        ax.plot([line.start[0], line.end[0]], [line.start[1], line.end[1]], color=LINE_COLOUR,
                linewidth=2.2, solid_capstyle="round")
        middle = (line.start + line.end) / 2
        assert line.direction is not None
        arrow = line.direction * min(1.5, 0.25 * line.length + 0.5)
        tip = middle + arrow
        ax.annotate("", xy=(float(tip[0]), float(tip[1])),
                    xytext=(float(middle[0]), float(middle[1])),
                    arrowprops={"arrowstyle": "->", "color": LINE_COLOUR, "linewidth": 1.5})
        if labels:
            ax.text(line.end[0], line.end[1], f" {line.name} (+)", color=LINE_COLOUR,
                    fontsize=8, ha="left", va="center")


def plot_site(
    places: Places, tracks: Tracks | None = None, title: str = "", ax: Axes | None = None
) -> Figure:
    """Trajectories (thin grey, start dot green, end dot red) under the places."""
    figure, ax = _axes(ax, (6.0, 7.5))
    if tracks is not None and len(tracks):
        order = np.lexsort((tracks.timestamp, tracks.track_id))
        ids, xy = tracks.track_id[order], tracks.world_xy[order]
        cuts = np.flatnonzero(np.diff(ids)) + 1
        for piece in np.split(xy, cuts):
            ax.plot(piece[:, 0], piece[:, 1], color="0.55", linewidth=0.6, alpha=0.8)
            ax.plot(*piece[0], "o", color="tab:green", markersize=2)
            ax.plot(*piece[-1], "o", color="tab:red", markersize=2)
    draw_places(ax, places)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, linewidth=0.3)
    ax.set_title(title or "places and trajectories (start green, end red)")
    return figure


def plot_counts_over_time(result: AnalyticsResult, axes: list[Axes] | None = None) -> Figure:
    """Crossings per time bin (one colour per line: positive solid, negative dashed) and,
    below, zone entries per bin (all classes)."""
    interval = result.summary["settings"]["interval_s"]
    lines: dict[tuple[str, str], dict[float, int]] = defaultdict(lambda: defaultdict(int))
    zones: dict[str, dict[float, int]] = defaultdict(lambda: defaultdict(int))
    for row in result.counts_over_time:
        if row["kind"] in ("positive", "negative"):
            lines[(row["place"], row["kind"])][row["bin_start_s"]] += row["count"]
        elif row["kind"] == "entries":
            zones[row["place"]][row["bin_start_s"]] += row["count"]
    line_names = [row["line"] for row in result.lines if row["class"] == "all"]
    line_names = list(dict.fromkeys(line_names))
    zone_names = [row["zone"] for row in result.zones]
    panels = [name for name, present in (("lines", line_names), ("zones", zone_names)) if present]
    if axes is None:
        # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        figure = Figure(figsize=(8.0, 2.6 * max(len(panels), 1) + 0.6), layout="constrained")
        FigureCanvasAgg(figure)
        axes = list(figure.subplots(max(len(panels), 1), 1, squeeze=False, sharex=True)[:, 0])
    else:
        figure = axes[0].figure  # type: ignore[assignment]
    starts = [start for series in (*lines.values(), *zones.values()) for start in series]
    end = result.summary.get("end_s") or 0.0
    first = min(starts) if starts else 0.0
    last = max(max(starts, default=first), end)
    calendar = result.calendar
    bins: Any = np.arange(first, last + interval, interval)
    times: Any = bins
    if calendar is not None:
        # Local bins differ in length on daylight-saving days: follow them, and draw them
        # at their local wall-clock times.
        time_bins = TimeBins(interval, calendar)
        key, bins = time_bins.key(first), []
        while time_bins.start(key) <= last:
            bins.append(time_bins.start(key))
            key = time_bins.following(key)
        times = [calendar.local(start) for start in bins]
    for ax, panel in zip(axes, panels, strict=False):
        if panel == "lines":
            for index, name in enumerate(line_names):
                colour = f"C{index % 10}"
                for direction, style in (("positive", "-"), ("negative", "--")):
                    counts = [lines[(name, direction)].get(start, 0) for start in bins]
                    ax.step(times, counts, where="post", linestyle=style, color=colour,
                            label=f"{name} {'+' if direction == 'positive' else '-'}")
            ax.set_ylabel("crossings per bin")
            ax.set_title("line crossings over time (+ solid, - dashed)")
        else:
            for index, name in enumerate(zone_names):
                counts = [zones[name].get(start, 0) for start in bins]
                ax.step(times, counts, where="post",
                        color=ZONE_COLOURS[index % len(ZONE_COLOURS)], label=name)
            ax.set_ylabel("entries per bin")
            ax.set_title("zone entries over time")
        ax.legend(fontsize=7, ncols=3, loc="upper left")
        ax.grid(True, linewidth=0.3)
    if calendar is None:
        axes[-1].set_xlabel(f"time (s), bins of {interval:g} s")
    else:
        # lazy, as above
        from matplotlib.dates import AutoDateLocator, ConciseDateFormatter

        locator = AutoDateLocator(tz=calendar.zone)
        axes[-1].xaxis.set_major_locator(locator)
        axes[-1].xaxis.set_major_formatter(ConciseDateFormatter(locator, tz=calendar.zone))
        axes[-1].set_xlabel(f"local time ({calendar.timezone}), bins of {interval:g} s")
    return figure


def plot_dwell(result: AnalyticsResult, ax: Axes | None = None) -> Figure:
    """Histogram of dwell per visit, one colour per zone (complete visits solid)."""
    figure, ax = _axes(ax, (7.0, 4.0))
    by_zone: dict[str, list[float]] = defaultdict(list)
    for visit in result.visits:
        by_zone[visit.zone].append(visit.dwell_s)
    values = [dwell for dwells in by_zone.values() for dwell in dwells]
    if not values:
        ax.text(0.5, 0.5, "no visits", ha="center", va="center", transform=ax.transAxes)
    else:
        edges = np.histogram_bin_edges(values, bins=min(30, max(5, len(values) // 3))).tolist()
        zones = [row["zone"] for row in result.zones]
        ax.hist([by_zone[zone] for zone in zones], bins=edges, label=zones,
                color=[ZONE_COLOURS[zones.index(zone) % len(ZONE_COLOURS)] for zone in zones],
                histtype="barstacked", alpha=0.8)
        ax.legend(fontsize=8)
    ax.set_xlabel("dwell per visit (s)")
    ax.set_ylabel("visits")
    ax.set_title("dwell time per visit")
    ax.grid(True, linewidth=0.3)
    return figure


def plot_heatmap(
    result: AnalyticsResult, grid: HeatmapGrid, places: Places | None = None,
    ax: Axes | None = None, site_map: tuple[np.ndarray, tuple[float, float, float, float]]
    | None = None,
) -> Figure:
    """Person-seconds per cell on the metric grid, places drawn on top.

    Args:
        site_map: ``(RGB image, (x_min, x_max, y_min, y_max) metres)`` drawn underneath.
    """
    figure, ax = _axes(ax, (6.0, 7.5))
    heat = result.heatmap if result.heatmap is not None else np.zeros(grid.shape)
    shown = np.ma.masked_where(heat <= 0, heat)
    if site_map is not None:
        ax.imshow(site_map[0], extent=site_map[1], origin="upper", alpha=0.6)
    image = ax.imshow(shown, origin="lower", extent=grid.extent, cmap="inferno_r",
                      interpolation="nearest", alpha=0.85 if site_map is not None else 1.0)
    figure.colorbar(image, ax=ax, label=f"person-seconds per {grid.cell_m:g} m cell",
                    shrink=0.8)
    if places is not None:
        draw_places(ax, places)
    ax.set_xlim(grid.extent[0], grid.extent[1])
    ax.set_ylim(grid.extent[2], grid.extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, linewidth=0.3)
    ax.set_title("occupancy heatmap")
    return figure


def plot_od(result: AnalyticsResult, ax: Axes | None = None) -> Figure:
    """Origin-destination matrix between zones (lives with two or more visits)."""
    names = list(result.od)
    figure, ax = _axes(ax, (1.4 * len(names) + 3.0, 1.1 * len(names) + 2.2))
    matrix = np.array([[result.od[origin][destination] for destination in names]
                       for origin in names]).reshape(len(names), len(names))
    ax.imshow(matrix, cmap="Blues", vmin=0)
    for row in range(len(names)):
        for column in range(len(names)):
            value = matrix[row, column]
            ax.text(column, row, str(value), ha="center", va="center",
                    color="white" if value > matrix.max() / 2 else "black")
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_yticks(range(len(names)),
                  [f"{name} ({result.od_unpaired[name]} unpaired)" for name in names])
    ax.set_xlabel("destination (zone of the last visit)")
    ax.set_ylabel("origin (zone of the first visit)")
    ax.set_title("origin-destination")
    return figure
