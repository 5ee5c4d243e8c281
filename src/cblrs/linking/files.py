"""``cblrs link``: planes' tracks (matcher databases or AI City files) -> global tracks.

The offline twin of the linker service: the same :class:`~cblrs.linking.PlaneLinker` fed
every plane's stored rows at once, and the same analytics settings, so its global tracks and
counts equal the service's on the same rows (tested).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics import AnalyticsConfig
from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.linking.linker import Handover, LinkedRows, LinkerConfig, link_tracks
from cblrs.linking.links import PlaneLink


class LinkInputError(CblrsError):
    """A plane's tracks cannot be read, or the inputs do not fit the site."""


@dataclass(frozen=True, eq=False)
class SiteLink:
    """What linking a site's planes gave.

    Attributes:
        rows: the global rows (time order).
        handovers: every hand-over decided.
        counters: the linker's counters (rows in and out, watched tracks, hand-overs, ...).
        planes: per input plane, the number of its tracks and of its rows.
    """

    rows: LinkedRows
    handovers: list[Handover]
    counters: dict[str, int]
    planes: dict[int, dict[str, int]]

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures: rows, global ids, hand-overs by kind, per plane."""
        kinds = Counter(item.kind for item in self.handovers)
        return {
            "rows": len(self.rows),
            "global_ids": len(np.unique(self.rows.tracks.track_id)),
            "handovers": dict(sorted(kinds.items())),
            "planes": {str(plane): figures for plane, figures in sorted(self.planes.items())},
            "counters": dict(sorted(self.counters.items())),
        }


def site_lost_after_s(links: Iterable[PlaneLink], default: float = 2.0) -> float:
    """How long a global track may go unseen and live on: longer than the longest portal
    transit (a person on the stairs is not gone), at least ``default`` seconds."""
    longest = max((link.transit_s[1] for link in links if link.portal), default=0.0)
    return max(float(default), longest + 1.0)


def site_analytics_config(links: Iterable[PlaneLink],
                          base: AnalyticsConfig | None = None) -> AnalyticsConfig:
    """The analytics settings of a site's global tracks: ``base`` (default settings) with
    lives that span its portals (:func:`site_lost_after_s`)."""
    base = base or AnalyticsConfig()
    return replace(base, lost_after_s=site_lost_after_s(links, base.lost_after_s))


def read_plane_tracks(path: str | Path, frames_per_second: float | None = None) -> Tracks:
    """A plane's tracks: a matcher's SQLite database (exact capture times) or an AI City text
    file (times from its frame numbers and ``frames_per_second`` or its sidecar).

    Raises:
        LinkInputError: the file is missing or neither.
    """
    path = Path(path)
    if not path.is_file():
        raise LinkInputError(f"{path} does not exist.")
    with path.open("rb") as handle:
        is_database = handle.read(16) == b"SQLite format 3\x00"
    if is_database:
        # lazy: the runtime (and its wire formats) only for databases
        from cblrs.runtime.matcher.store import RuntimeStore, StoreError

        try:
            with RuntimeStore(path, read_only=True) as store:
                return store.tracks()
        except StoreError as error:
            raise LinkInputError(str(error)) from None
    from cblrs.datasets.aicity import apply_track_metadata, read_track_metadata, read_tracks

    metadata = read_track_metadata(path)
    rate = frames_per_second or (metadata.frames_per_second if metadata else None)
    if rate is None:
        raise LinkInputError(
            f"{path} has no frame rate (no .meta.json sidecar): give --fps, or link the "
            "matchers' databases, whose capture times are exact."
        )
    return apply_track_metadata(read_tracks(path, rate), metadata)


def link_site(
    planes: Any,
    links: Iterable[PlaneLink],
    per_plane: Mapping[int, Tracks],
    config: LinkerConfig | None = None,
) -> SiteLink:
    """Link every plane's tracks (a :class:`~cblrs.plane.PlaneSet` and the site's links).

    Raises:
        LinkInputError: a plane that is not in the site.
    """
    for plane_id in per_plane:
        if plane_id not in planes.ids:
            raise LinkInputError(f"the site has no plane {plane_id} (planes: {planes.ids}).")
    rows, handovers, counters = link_tracks(planes, links, dict(per_plane), config)
    figures = {
        plane: {"tracks": len(np.unique(tracks.track_id)), "rows": len(tracks)}
        for plane, tracks in per_plane.items()
    }
    return SiteLink(rows, handovers, counters, figures)


def frames_per_second_of(per_plane: Mapping[int, Tracks]) -> float | None:
    """The frame rate the planes' rows share (frames over seconds), None if unknown."""
    rates = []
    for tracks in per_plane.values():
        if len(tracks) < 2:
            continue
        span = float(tracks.timestamp.max() - tracks.timestamp.min())
        frames = float(tracks.frame.max() - tracks.frame.min())
        if span > 0 and frames > 0:
            rates.append(frames / span)
    if not rates:
        return None
    rate = float(np.median(rates))
    return rate if math.isfinite(rate) else None
