"""``cblrs analytics``: a tracks file + a site file -> CSV/JSON tables and PNG plots."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.config import AnalyticsConfig, AnalyticsError, HeatmapGrid
from cblrs.analytics.site import (
    SitePlaces,
    check_tracks_on_site,
    load_site_places,
    site_extent,
    with_site_time,
)
from cblrs.analytics.tables import (
    AnalyticsResult,
    analyse_tracks,
    json_safe,
    open_private,
    write_result,
)
from cblrs.datasets.aicity import (
    TrackMetadata,
    apply_track_metadata,
    metadata_path,
    metadata_timestamps,
    read_track_metadata,
    read_tracks,
)
from cblrs.detections import Tracks
from cblrs.viz.analytics import plot_counts_over_time, plot_dwell, plot_heatmap, plot_od, plot_site

logger = logging.getLogger(__name__)

NICE_INTERVALS_S = (1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 21600, 86400)


def auto_interval(duration_s: float, bins: int = 40) -> float:
    """The smallest of :data:`NICE_INTERVALS_S` giving at most ``bins`` bins over the span."""
    for interval in NICE_INTERVALS_S:
        if duration_s / interval <= bins:
            return float(interval)
    return float(NICE_INTERVALS_S[-1])


def analyse_file(
    tracks_path: str | Path,
    site_path: str | Path,
    out: str | Path,
    frames_per_second: float | None = None,
    config: AnalyticsConfig | None = None,
    cell_m: float = 0.5,
    plots: bool = True,
    start: float | None = None,
) -> dict[str, Any]:
    """Run the analytics on an AI City tracks file with a site file's places.

    Args:
        tracks_path: AI City 2024 text file (its ``.meta.json`` sidecar, when present, gives
            the classes and frame rate).
        site_path: site file (YAML/JSON) with a ``places`` section.
        out: folder for the tables and plots (created).
        frames_per_second: rate of the file's frame numbers; needed unless the sidecar has
            it or keeps the rows' timestamps (the matcher's ``--out-tracks``).
        config: settings; ``interval_s`` is chosen from the data's span when left at its
            default and ``heatmap`` from the site's planes (or its places and the tracks).
        cell_m: heatmap cell, metres (when the grid is chosen here).
        plots: write the PNGs too.
        start: epoch seconds of the file's time 0 (scene seconds from frame numbers), so
            that its times are absolute. With absolute times (this, or the capture times of
            the matcher's sidecar) and a site ``timezone``, bins follow the local clock,
            tables carry local ISO times and only opening hours count; with scene seconds
            the site's time zone and hours are not applied (the summary says so).

    Returns:
        A summary: files written, counts per line and zone, settings.

    Raises:
        AnalyticsError: the site has no places, the tracks lie outside the site, no frame
            rate, or bad settings.
        DatasetError: the tracks file is missing or unreadable.
    """
    site = load_site_places(site_path)
    if len(site.places) == 0:
        raise AnalyticsError(
            f"{site_path} has no places, so there is nothing to count: add zones or lines "
            "under places: (see sites/wildtrack.yaml)."
        )
    tracks = read_tracks(tracks_path)  # a missing or malformed file is reported first
    metadata = read_track_metadata(tracks_path)
    tracks, rate = _timed(tracks, tracks_path, metadata, frames_per_second)
    absolute = rate is None or start is not None
    if start is not None:
        if not math.isfinite(start):
            raise AnalyticsError(f"the start time must be finite, got {start}.")
        tracks = replace(tracks, timestamp=tracks.timestamp + start)
    tracks = apply_track_metadata(tracks, metadata)
    if len(tracks) == 0:
        raise AnalyticsError(f"{tracks_path} holds no track rows.")
    outside = check_tracks_on_site(tracks, site)
    config = config or AnalyticsConfig()
    span = float(tracks.timestamp.max() - tracks.timestamp.min())
    if config.interval_s == AnalyticsConfig().interval_s:
        config = replace(config, interval_s=auto_interval(span))
    local_time = "none: the site has no timezone"
    if site.timezone is not None:
        if absolute:
            config = with_site_time(config, site)
            local_time = site.timezone
        else:
            local_time = ("not applied: the times are scene seconds (give the time of "
                          "second 0 with --start)")
    if config.heatmap is None:
        config = replace(config, heatmap=HeatmapGrid.covering(_heatmap_bounds(site, tracks),
                                                              cell_m))
    result = analyse_tracks(tracks, site.places, config)
    files = write_result(result, out)
    if plots:
        files += write_plots(result, site.places, tracks, config, out, site)
    summary = {
        "tracks": str(tracks_path),
        "site": site.name or str(site_path),
        "rows": len(tracks),
        "track_ids": len(np.unique(tracks.track_id)),
        "rows_outside_site": outside,
        "frames_per_second": rate,
        "classes_known": bool((tracks.class_id >= 0).any()),
        "seconds": span,
        "local_time": local_time,
        "closed_events": result.summary["closed_events"],
        "lines": [row for row in result.lines if row["class"] == "all"],
        "zones": result.zones,
        "od": result.od,
        "settings": config.to_dict(),
        "files": [str(path) for path in files],
    }
    return json_safe(summary)


def _timed(
    tracks: Tracks, tracks_path: str | Path, metadata: TrackMetadata | None,
    frames_per_second: float | None,
) -> tuple[Tracks, float | None]:
    """The tracks with their times in seconds and the frame rate used (None: the sidecar's
    own timestamps, as the matcher's --out-tracks keeps them). ``--fps`` wins over both."""
    if frames_per_second is None:
        timestamps = metadata_timestamps(tracks, metadata)
        if timestamps is not None:
            return replace(tracks, timestamp=timestamps), None
    rate = frames_per_second
    if rate is None and metadata is not None:
        rate = metadata.frames_per_second
    if rate is None:
        where = (
            "no .meta.json sidecar (cblrs track and cblrs matcher --out-tracks write one)"
            if metadata is None
            else f"its sidecar {metadata_path(tracks_path).name} has neither a frame rate "
            "nor timestamps"
        )
        raise AnalyticsError(
            f"{tracks_path} carries no time: {where}; give --fps, the frames per second of "
            "its frame numbers."
        )
    if not (math.isfinite(rate) and rate > 0):
        raise AnalyticsError(f"--fps must be a positive number, got {rate}.")
    return replace(tracks, timestamp=tracks.frame / rate), rate


def _heatmap_bounds(site, tracks) -> tuple[float, float, float, float]:
    if site.planes:
        return site_extent(site)
    x0, y0, x1, y1 = site_extent(site)
    # Without planes, the places and the bulk of the tracks (robust to a few stray rows).
    low = np.percentile(tracks.world_xy, 0.5, axis=0)
    high = np.percentile(tracks.world_xy, 99.5, axis=0)
    return (min(x0, low[0]), min(y0, low[1]), max(x1, high[0]), max(y1, high[1]))


def write_plots(
    result: AnalyticsResult, places, tracks, config: AnalyticsConfig, out: str | Path,
    site: SitePlaces | None = None,
) -> list[Path]:
    """counts_over_time.png, dwell.png, heatmap.png, od.png (two zones or more), places.png."""

    out = Path(out)
    figures = {
        "places.png": plot_site(places, tracks),
        "counts_over_time.png": plot_counts_over_time(result),
    }
    if places.zones:
        figures["dwell.png"] = plot_dwell(result)
    if config.heatmap is not None:
        background = None
        if site is not None and site.map_image is not None and site.map_extent is not None:
            # lazy: OpenCV takes ~80 ms to import; only this path needs it
            import cv2

            picture = cv2.imread(str(site.map_image), cv2.IMREAD_COLOR)
            if picture is not None:
                background = (cv2.cvtColor(picture, cv2.COLOR_BGR2RGB), site.map_extent)
        figures["heatmap.png"] = plot_heatmap(result, config.heatmap, places,
                                              site_map=background)
    if len(places.zones) >= 2:
        figures["od.png"] = plot_od(result)
    written = []
    for name, figure in figures.items():
        path = out / name
        with open_private(path, "wb") as handle:  # plots of people's movements too
            figure.savefig(handle, dpi=110, format="png")
        written.append(path)
    return written
