"""How well a track that starts on one plane continues one that another plane saw.

Pure functions of the two tracks' recent rows (``(t, x, y)`` samples, seconds and metres) and
the link between the planes; :class:`~cblrs.linking.PlaneLinker` calls them for every
candidate and keeps the lowest score. ``None`` means "cannot be the same object".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from cblrs.linking.links import PlaneLink

Sample = tuple[float, float, float]
"""One row of a track: (seconds, x metres, y metres)."""


@dataclass(frozen=True)
class LinkerConfig:
    """How the linker decides (see the module docstring).

    Attributes:
        decision_s: how long a track that starts in a hand-over region is watched before its
            id is decided (also the delay it adds).
        time_tolerance_s: rows of two planes this close in time are of the same instant.
        velocity_window_s: a track's velocity is taken over its last rows within this span.
        velocity_weight_s: metres of score per m/s of velocity difference (overlap links).
        portal_sigma_s: the smallest time unit a portal transit is scored in (seconds).
        portal_sigma_fraction: the time unit grows with the expected transit time.
        portal_gate: at most this many time units between expected and observed transit.
        forget_after_s: a track unseen this long is forgotten (rows after that start anew).
    """

    decision_s: float = 1.0
    time_tolerance_s: float = 0.05
    velocity_window_s: float = 1.0
    velocity_weight_s: float = 0.5
    portal_sigma_s: float = 1.0
    portal_sigma_fraction: float = 0.3
    portal_gate: float = 3.0
    forget_after_s: float = 120.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        if self.forget_after_s < self.decision_s:
            raise ValueError("forget_after_s must be at least decision_s")



def overlap_score(
    new_rows: Sequence[Sample],
    old_rows: Sequence[Sample],
    new_first_t: float,
    new_first_xy: tuple[float, float],
    old_last_t: float,
    old_last_xy: tuple[float, float],
    link: PlaneLink,
    config: LinkerConfig,
) -> float | None:
    """Score of an overlap hand-over; the rows are those up to the decision.

    Seen together (rows within ``time_tolerance_s``): the mean distance between the two
    planes' rows over ``max_distance_m`` (at most 1), plus ``velocity_weight_s`` x the
    velocity difference. Not seen together (the old track ended first, within the link's
    ``transit_s``): 1 + where the old track's last velocity would have taken it against where
    the new one starts, over what that distance may be (1 or more: a track seen together
    always wins over one that was not).
    """
    if not new_rows:
        return None
    tolerance = config.time_tolerance_s
    distances = np.zeros(0)
    if old_rows:
        old = np.asarray(old_rows, dtype=np.float64)  # (M, 3), in time order
        new = np.asarray(new_rows, dtype=np.float64)
        # The old row nearest in time to each new row: the one before or after it.
        after = np.clip(np.searchsorted(old[:, 0], new[:, 0]), 0, len(old) - 1)
        before = np.clip(after - 1, 0, len(old) - 1)
        nearest = np.where(np.abs(old[before, 0] - new[:, 0]) <= np.abs(old[after, 0]
                                                                         - new[:, 0]),
                           before, after)
        together = np.abs(old[nearest, 0] - new[:, 0]) <= tolerance
        distances = np.hypot(*(old[nearest[together], 1:] - new[together, 1:]).T)
    velocity_gap = _gap(velocity(new_rows, config.velocity_window_s),
                        velocity(old_rows, config.velocity_window_s))
    if len(distances):
        mean = float(np.mean(distances))
        if mean > link.max_distance_m:
            return None
        return mean / link.max_distance_m + config.velocity_weight_s * velocity_gap
    gap = new_first_t - old_last_t
    if not link.transit_s[0] - tolerance <= gap <= link.transit_s[1] + tolerance:
        return None
    moving = velocity(old_rows, config.velocity_window_s)
    predicted = (old_last_xy[0] + moving[0] * gap, old_last_xy[1] + moving[1] * gap)
    error = math.hypot(predicted[0] - new_first_xy[0], predicted[1] - new_first_xy[1])
    allowed = link.max_distance_m + 1.0 * gap  # 1 m/s of unseen change of pace
    if error > allowed:
        return None
    return 1.0 + error / allowed + config.velocity_weight_s * velocity_gap


def portal_score(
    old_plane: int,
    new_first_t: float,
    new_first_xy: tuple[float, float],
    old_last_t: float,
    old_last_xy: tuple[float, float],
    old_rows: Sequence[Sample],
    link: PlaneLink,
    config: LinkerConfig,
) -> float | None:
    """Score of a portal hand-over: the old track (on ``old_plane``) ended in its portal, the
    new one started in the other ``transit_s`` later; how far the time it took is from the
    time the distance would take at the old track's last speed, in units of
    ``max(portal_sigma_s, portal_sigma_fraction x expected)``, over ``portal_gate`` (at
    most 1)."""
    gap = new_first_t - old_last_t
    if not link.transit_s[0] <= gap <= link.transit_s[1]:
        return None
    if not bool(link.in_region(old_plane, np.array([old_last_xy]))[0]):
        return None
    speed = max(math.hypot(*velocity(old_rows, config.velocity_window_s)), 0.3)
    distance = math.hypot(new_first_xy[0] - old_last_xy[0], new_first_xy[1] - old_last_xy[1])
    expected = distance / speed
    sigma = max(config.portal_sigma_s, config.portal_sigma_fraction * expected)
    units = abs(gap - expected) / sigma
    if units > config.portal_gate:
        return None
    return units / config.portal_gate


def velocity(history: Sequence[tuple[float, float, float]], window_s: float
              ) -> tuple[float, float]:
    """(vx, vy) m/s over the last ``window_s`` of (t, x, y) rows (0 with less than 0.2 s)."""
    if len(history) < 2:
        return (0.0, 0.0)
    last = history[-1]
    first = next(item for item in history if item[0] >= last[0] - window_s)
    span = last[0] - first[0]
    if span < 0.2:
        return (0.0, 0.0)
    return ((last[1] - first[1]) / span, (last[2] - first[2]) / span)


def _gap(first: tuple[float, float], second: tuple[float, float]) -> float:
    return math.hypot(first[0] - second[0], first[1] - second[1])


