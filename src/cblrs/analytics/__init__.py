"""Analytics on global tracks: line counts, zone visits and dwell, occupancy, OD, heatmap.

The engine (:class:`Analytics`) is incremental — the same object runs offline on a whole
tracks file and online on each matcher update, with a JSON-serialisable state — and the
offline entry point :func:`analyse_tracks` is just the engine fed once and flushed.
"""

from cblrs.analytics.config import (
    AnalyticsConfig,
    AnalyticsError,
    Event,
    HeatmapGrid,
    LineCrossing,
    ZoneEntered,
    ZoneLeft,
)
from cblrs.analytics.engine import Analytics
from cblrs.analytics.tables import AnalyticsResult, analyse_tracks, write_result

__all__ = [
    "Analytics",
    "AnalyticsConfig",
    "AnalyticsError",
    "AnalyticsResult",
    "Event",
    "HeatmapGrid",
    "LineCrossing",
    "ZoneEntered",
    "ZoneLeft",
    "analyse_tracks",
    "write_result",
]

_SITE_NAMES = ("SitePlaces", "check_tracks_on_site", "load_site_places")


def __getattr__(name: str):
    """The site helpers of :mod:`cblrs.analytics.site` (documented there, so not in
    ``__all__``), imported on first use: they load :mod:`cblrs.site`, whose schema models take
    a third of a second of CPU to build, and a matcher without a site never needs them."""
    if name in _SITE_NAMES:
        import importlib

        return getattr(importlib.import_module("cblrs.analytics.site"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
