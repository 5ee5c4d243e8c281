"""Matching: camera messages in, global world tracks out (the paper's central node).

Two matchers share one interface (:class:`Matcher`):

* ``"paper"`` — :class:`PaperMatcher`, the paper's colour-distance Hungarian matcher;
* ``"fusion"`` — :class:`FusionTracker` (default), cross-camera fusion + Kalman tracking.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cblrs.matching.base import Matcher, MatcherError
from cblrs.matching.fusion import FusionConfig, FusionTracker
from cblrs.matching.paper import PaperConfig, PaperMatcher
from cblrs.plane import PlaneSet

MATCHERS: dict[str, type] = {"fusion": FusionTracker, "paper": PaperMatcher}
DEFAULT_MATCHER = "fusion"


def make_matcher(
    name: str, planes: PlaneSet, camera_ids: Sequence[str], **options: Any
) -> Matcher:
    """Build a matcher by name.

    Args:
        name: ``"fusion"`` or ``"paper"``.
        planes: the planes the cameras' colours refer to.
        camera_ids: camera names; ``Tracks.camera_id`` indexes this list.
        **options: the matcher's config fields (:class:`FusionConfig`, :class:`PaperConfig`).

    Raises:
        MatcherError: unknown name or invalid options.

    Example:
        >>> from cblrs.plane import PlaneSet, PlaneSpec
        >>> planes = PlaneSet([PlaneSpec(1, (0, 0), 20, 20)])
        >>> make_matcher("fusion", planes, ["cam1", "cam2"]).update(0.0, []).track_id.tolist()
        []
    """
    try:
        matcher_type = MATCHERS[name]
    except KeyError:
        raise MatcherError(
            f"unknown matcher {name!r}; choose one of: {', '.join(MATCHERS)}."
        ) from None
    return matcher_type(planes, camera_ids, **options)


__all__ = [
    "DEFAULT_MATCHER",
    "MATCHERS",
    "FusionConfig",
    "FusionTracker",
    "Matcher",
    "MatcherError",
    "PaperConfig",
    "PaperMatcher",
    "make_matcher",
]
