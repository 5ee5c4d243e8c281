"""Zones and counting lines: geometry and the one-sentence errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from cblrs.places import CountingLine, PlaceError, Places, Zone, bounding_box


def test_zone_contains_points_inside_and_not_outside():
    zone = Zone("square", [[0, 0], [4, 0], [4, 4], [0, 4]])
    inside = zone.contains([[1, 1], [3.9, 0.1], [5, 5], [-1, 2], [2, 4.5]])
    assert inside.tolist() == [True, True, False, False, False]
    assert zone.area == pytest.approx(16.0)


def test_zone_concave_polygon():
    # an L shape: the notch (3, 3) is outside
    zone = Zone("L", [[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]])
    assert zone.contains([[3, 3], [1, 3], [3, 1]]).tolist() == [False, True, True]


def test_zone_closed_ring_is_accepted_once():
    zone = Zone("tri", [[0, 0], [1, 0], [0, 1], [0, 0]])
    assert len(zone.polygon) == 3


@pytest.mark.parametrize(
    ("polygon", "message"),
    [
        ([[0, 0], [1, 1]], "at least 3 vertices"),
        ([[0, 0], [2, 2], [2, 0], [0, 2]], "intersects itself"),
        ([[0, 0], [1, 1], [2, 2]], "zero area"),
        ([[0, 0], [1, np.nan], [2, 2]], "not a finite number"),
        ("abc", "list of [x, y] points"),
    ],
)
def test_zone_errors_name_the_zone(polygon, message):
    with pytest.raises(PlaceError, match=re.escape(message)) as error:
        Zone("plaza", polygon)
    assert "plaza" in str(error.value) or "vertices" in message


def test_line_signed_distance_and_default_direction():
    line = CountingLine("gate", (0, 0), (0, 4))
    assert line.signed_distance([[1, 2], [-1, 2]]).tolist() == [-1.0, 1.0]
    assert line.along([[0, 0], [0, 4], [0, 8]]).tolist() == [0.0, 1.0, 2.0]
    assert line.length == pytest.approx(4.0)


def test_line_direction_hint_flips_the_positive_side():
    line = CountingLine("gate", (0, 0), (0, 4), direction=(1, 0.3))
    assert line.signed_distance([[1, 2]]).tolist() == [1.0]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"start": (1, 1), "end": (1, 1)}, "zero length"),
        ({"start": (0, 0), "end": (0, 4), "direction": (0, 2)}, "parallel"),
        ({"start": (0, 0), "end": (0, 4), "hysteresis_m": -1.0}, "hysteresis_m"),
    ],
)
def test_line_errors(kwargs, message):
    with pytest.raises(PlaceError, match=re.escape(message)):
        CountingLine("gate", **kwargs)


def test_places_names_are_unique_and_bounding_box():
    zone = Zone("a", [[0, 0], [1, 0], [1, 1]])
    line = CountingLine("b", (2, 2), (3, 5))
    places = Places((zone,), (line,))
    assert places.names == ["a", "b"]
    assert bounding_box(places) == (0.0, 0.0, 3.0, 5.0)
    assert bounding_box(Places()) is None
    with pytest.raises(PlaceError, match="named 'a'"):
        Places((zone,), (CountingLine("a", (0, 0), (1, 0)),))
    with pytest.raises(PlaceError, match="no zone named"):
        places.zone("x")


def test_places_round_trip_through_dict():
    places = Places(
        (Zone("a", [[0, 0], [1, 0], [1, 1]], plane_id=1),),
        (CountingLine("b", (2, 2), (3, 5), direction=(1, 0), hysteresis_m=0.3),),
    )
    again = Places.from_dict(places.to_dict())
    assert again.to_dict() == places.to_dict()


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"zones": [], "gates": []}, "places.gates: unknown key"),
        (
            {"zones": [{"name": "a", "polygon": [[0, 0], [1, 0], [1, 1]], "colour": 1}]},
            "places.zones[0].colour: unknown key",
        ),
        ({"lines": [{"name": "b", "start": [0, 0]}]}, "places.lines[0] (b) has no end"),
        ([], "must be a mapping"),
    ],
)
def test_places_from_dict_errors_name_the_path(data, message):
    with pytest.raises(PlaceError, match=re.escape(message)):
        Places.from_dict(data)


def test_zone_hysteresis_round_trips_and_is_validated():
    places = Places.from_dict(
        {"zones": [{"name": "a", "polygon": [[0, 0], [1, 0], [1, 1]], "hysteresis_m": 0.25}]}
    )
    assert places.zones[0].hysteresis_m == 0.25
    assert Places.from_dict(places.to_dict()).to_dict() == places.to_dict()
    with pytest.raises(PlaceError, match="zone 'a': hysteresis_m must be a number >= 0"):
        Zone("a", [[0, 0], [1, 0], [1, 1]], hysteresis_m=-1.0)


def test_zone_signed_distance_is_positive_inside_and_measured_to_the_nearest_edge():
    square = Zone("s", [[0, 0], [4, 0], [4, 4], [0, 4]])
    distance = square.signed_distance([[1, 2], [2, 2], [-1, 2], [6, 7], [2, 0]])
    assert distance[:4] == pytest.approx([1.0, 2.0, -1.0, -np.hypot(2, 3)])
    assert abs(distance[4]) < 1e-12
