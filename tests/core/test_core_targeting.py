"""Box -> target pixel."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.targeting import DEFAULT_TARGETING, TargetingPosition, target_pixels, targeting_for

SIZE = (640, 480)


@pytest.mark.parametrize(
    ("box", "horizontal", "vertical", "pixel", "inside"),
    [
        ((100, 50, 140, 250), 0.5, 1.0, (120, 250), True),  # foot point
        ((100, 50, 140, 250), 0.5, 0.5, (120, 150), True),  # box centre
        ((100, 50, 140, 250), 0.0, 0.0, (100, 50), True),  # top-left corner
        ((100, 50, 140, 250), 0.5, 0.95, (120, 240), True),  # the paper's VTP 95 %
        ((100, 50, 100, 50), 0.5, 1.0, (100, 50), True),  # degenerate: a point
        ((600, 300, 700, 400), 0.5, 1.0, (639, 400), False),  # foot right of the image
        ((-50, 300, 30, 400), 0.25, 1.0, (0, 400), False),  # foot left of the image
        ((-50, 300, 30, 400), 0.5, 1.0, (-10 + 0.0, 400), False),  # clamped below
        ((200, 300, 240, 520), 0.5, 1.0, (220, 479), False),  # foot below the image
        ((200, 300, 240, 480), 0.5, 1.0, (220, 479), True),  # foot on the bottom edge
        ((200, -90, 240, -10), 0.5, 1.0, (220, 0), False),  # box above the image
        ((140, 50, 100, 250), 0.5, 1.0, (120, 250), False),  # x_max < x_min
        ((np.nan, 50, 100, 250), 0.5, 1.0, None, False),  # not a number
    ],
)
def test_target_pixels(box, horizontal, vertical, pixel, inside):
    pixels, flags = target_pixels(np.array([box], dtype=float), horizontal, vertical, SIZE)
    assert flags.tolist() == [inside]
    if pixel is not None:
        expected = np.clip(np.array(pixel, dtype=float), 0, [SIZE[0] - 1, SIZE[1] - 1])
        np.testing.assert_allclose(pixels[0], expected)
    # Targets of valid boxes always lie inside the image after clamping.
    if np.isfinite(box).all():
        assert 0 <= pixels[0, 0] <= SIZE[0] - 1 and 0 <= pixels[0, 1] <= SIZE[1] - 1


def test_without_image_size_nothing_is_clamped():
    pixels, inside = target_pixels(np.array([[-50.0, 300, 30, 400]]), 0.0, 1.0)
    np.testing.assert_allclose(pixels, [[-50.0, 400.0]])
    assert inside.tolist() == [True]


def test_empty_boxes():
    pixels, inside = target_pixels(np.zeros((0, 4)), image_size=SIZE)
    assert pixels.shape == (0, 2) and inside.shape == (0,)


def test_per_box_targeting_positions():
    boxes = np.array([[0.0, 0, 10, 100], [0.0, 0, 10, 100]])
    pixels, _ = target_pixels(boxes, np.array([0.5, 1.0]), np.array([1.0, 0.5]))
    np.testing.assert_allclose(pixels, [[5.0, 100.0], [10.0, 50.0]])


@pytest.mark.parametrize("shape", [(4,), (2, 3), (1, 5)])
def test_bad_box_shapes(shape):
    with pytest.raises(ValueError, match=r"xyxy must have shape \(N, 4\)"):
        target_pixels(np.zeros(shape))


@pytest.mark.parametrize(
    ("name", "expected"),
    [("person", (0.5, 1.0)), ("car", (0.5, 0.85)), ("unknown thing", (0.5, 1.0))],
)
def test_targeting_defaults(name, expected):
    position = targeting_for(name)
    assert (position.horizontal, position.vertical) == expected
    assert "person" in DEFAULT_TARGETING


@pytest.mark.parametrize("values", [(-0.1, 1.0), (0.5, 1.5)])
def test_targeting_position_range(values):
    with pytest.raises(ValueError, match=r"targeting position must be within 0\.\.1"):
        TargetingPosition(*values)
