"""Colour plane: encode/decode round trips, validity, several planes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.errors import PlaneError
from cblrs.plane import PlaneSet, PlaneSpec

PLANES = {
    8: PlaneSpec(3, (-3.0, -9.0), 12.0, 36.0, bits=8),
    16: PlaneSpec(3, (-3.0, -9.0), 12.0, 36.0, bits=16),
}


def points_on(plane: PlaneSpec):
    x0, y0 = plane.origin
    return st.tuples(
        st.floats(x0, x0 + plane.width, allow_nan=False),
        st.floats(y0, y0 + plane.length, allow_nan=False),
    )


@pytest.mark.parametrize("bits", [8, 16])
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_round_trip_error_at_most_half_a_step(bits, data):
    plane = PLANES[bits]
    point = np.array([data.draw(points_on(plane))])
    colours, valid = plane.encode(point)
    assert valid.all()
    assert colours.max() <= plane.max_value
    decoded, decoded_valid = plane.decode(colours)
    assert decoded_valid.all()
    # decode . encode is idempotent: a decoded point encodes to the same colour.
    again, _ = plane.encode(decoded)
    np.testing.assert_array_equal(again, colours)
    step_x, step_y = plane.step
    error = np.abs(decoded - point)[0]
    # Half a step, plus float rounding of the multiply-add.
    assert error[0] <= step_x / 2 * (1 + 1e-9) + 1e-12
    assert error[1] <= step_y / 2 * (1 + 1e-9) + 1e-12


@pytest.mark.parametrize("bits", [8, 16])
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_decode_then_encode_is_idempotent(bits, data):
    plane = PLANES[bits]
    red = data.draw(st.integers(0, plane.max_value))
    green = data.draw(st.integers(0, plane.max_value))
    colours = np.array([[red, green, plane.plane_id]])
    world_xy, valid = plane.decode(colours)
    assert valid.all()
    again, again_valid = plane.encode(world_xy)
    assert again_valid.all()
    np.testing.assert_array_equal(again, colours)


@pytest.mark.parametrize(
    ("point", "expected_valid"),
    [
        ((-3.0, -9.0), True),  # corner
        ((9.0, 27.0), True),  # opposite corner
        ((-3.001, 0.0), False),
        ((0.0, 27.001), False),
        ((np.nan, 0.0), False),
        ((np.inf, 0.0), False),
    ],
)
def test_points_off_the_plane_are_invalid(point, expected_valid):
    plane = PLANES[16]
    colours, valid = plane.encode(np.array([point]))
    assert valid[0] == expected_valid
    if not expected_valid:
        assert colours[0].tolist() == [0, 0, 0]


def test_empty_input():
    plane = PLANES[8]
    colours, valid = plane.encode(np.zeros((0, 2)))
    assert colours.shape == (0, 3) and valid.shape == (0,)
    world_xy, valid = plane.decode(np.zeros((0, 3), dtype=np.int64))
    assert world_xy.shape == (0, 2) and valid.shape == (0,)


def test_step_is_size_over_levels():
    assert PLANES[8].step == pytest.approx((12.0 / 255, 36.0 / 255))
    assert PLANES[16].step == pytest.approx((12.0 / 65535, 36.0 / 65535))


@pytest.mark.parametrize(
    ("colour", "valid"),
    [
        ((0, 0, 0), False),  # B = 0: no location
        ((10, 10, 2), False),  # another plane's id
        ((10, 10, 3), True),
        ((256, 10, 3), False),  # beyond 8 bits
    ],
)
def test_decode_validity(colour, valid):
    _, decoded_valid = PLANES[8].decode(np.array([colour]))
    assert decoded_valid[0] == valid


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"bits": 12}, "bits per channel must be 8 or 16, got 12"),
        ({"plane_id": 0}, "plane id must be 1..65535"),
        ({"plane_id": 256, "bits": 8}, "plane id must be 1..255"),
        ({"width": 0.0}, "width and length must be positive"),
        ({"length": -1.0}, "width and length must be positive"),
        ({"origin": (np.nan, 0.0)}, "must be finite"),
    ],
)
def test_invalid_plane_specs(kwargs, message):
    arguments = {"plane_id": 1, "origin": (0.0, 0.0), "width": 10.0, "length": 10.0}
    arguments.update(kwargs)
    with pytest.raises(PlaneError, match=message.replace("(", r"\(").replace(")", r"\)")):
        PlaneSpec(**arguments)


def test_plane_set_decodes_each_plane_by_its_id():
    ground = PlaneSpec(1, (0.0, 0.0), 10.0, 10.0, bits=8)
    table = PlaneSpec(2, (2.0, 2.0), 1.0, 2.0, bits=8, height=0.8)
    planes = PlaneSet([ground, table])
    colours = np.array([[255, 0, 1], [255, 0, 2], [5, 5, 0], [5, 5, 9]])
    world_xy, valid, plane_ids = planes.decode(colours)
    assert valid.tolist() == [True, True, False, False]
    assert plane_ids.tolist() == [1, 2, 0, 0]
    np.testing.assert_allclose(world_xy[:2], [[10.0, 0.0], [3.0, 2.0]])
    assert np.isnan(world_xy[2:]).all()


@pytest.mark.parametrize(
    ("planes", "message"),
    [
        ([], "at least one plane"),
        (
            [PlaneSpec(1, (0, 0), 1, 1), PlaneSpec(1, (5, 5), 1, 1)],
            r"plane ids must be distinct, got \[1, 1\]",
        ),
        (
            [PlaneSpec(1, (0, 0), 1, 1, bits=8), PlaneSpec(2, (5, 5), 1, 1, bits=16)],
            "same bit depth",
        ),
    ],
)
def test_invalid_plane_sets(planes, message):
    with pytest.raises(PlaneError, match=message):
        PlaneSet(planes)


def test_spec_round_trips_through_dict():
    plane = PlaneSpec(7, (1.5, -2.0), 3.0, 4.0, bits=8, height=1.2, name="table")
    assert PlaneSpec.from_dict(plane.to_dict()) == plane
    with pytest.raises(PlaneError, match="unknown plane field"):
        PlaneSpec.from_dict({**plane.to_dict(), "colour": "red"})


def test_around_covers_the_points_with_margin():
    plane = PlaneSpec.around(np.array([[0.0, 0.0], [4.0, 2.0], [np.nan, 1.0]]), margin=1.0)
    assert plane.origin == (-1.0, -1.0)
    assert (plane.width, plane.length) == (6.0, 4.0)
    with pytest.raises(PlaneError, match="zero points"):
        PlaneSpec.around(np.zeros((0, 2)))


@pytest.mark.parametrize("bits, dtype", [(16, np.uint16), (16, np.int64), (8, np.uint8)])
def test_decode_valid_is_the_valid_rows_of_decode(bits, dtype):
    plane = PlaneSpec(2, (-3.0, 1.5), 12.0, 36.0, bits=bits)
    generator = np.random.default_rng(bits)
    top = plane.max_value if dtype != np.int64 else plane.max_value + 3
    colours = generator.integers(0, top + 1, (5000, 3)).astype(dtype)
    colours[::3, 2] = 2  # a third of this plane's colours, the rest mostly other planes'
    world_xy, valid = plane.decode(colours)
    assert 0 < valid.sum() < len(colours)
    np.testing.assert_array_equal(plane.decode_valid(colours), world_xy[valid])
    # Unsigned colours are read as they are: the same points as their int64 values.
    np.testing.assert_array_equal(plane.decode(colours.astype(np.int64))[0], world_xy)
    assert plane.decode_valid(np.zeros((0, 3), dtype)).shape == (0, 2)
