"""Shared fixtures of the analytics tests: a small site."""

from __future__ import annotations

import pytest

from cblrs.places import CountingLine, Places, Zone


@pytest.fixture
def square_places() -> Places:
    return Places(
        zones=(
            Zone("west", [[-8, -8], [-1, -8], [-1, 8], [-8, 8]]),
            Zone("east", [[1, -8], [8, -8], [8, 8], [1, 8]]),
            Zone("tiny", [[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5]], hysteresis_m=0.1),
        ),
        lines=(
            CountingLine("middle", (0, -6), (0, 6)),
            CountingLine("north", (-6, 3), (6, 3), hysteresis_m=0.2),
        ),
    )
