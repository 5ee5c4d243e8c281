"""The three localisers agree; pixels above the horizon are invalid everywhere."""

from __future__ import annotations

import numpy as np
import pytest
from core_cameras import posed_camera, wildtrack_plane

from cblrs.calibration import WILDTRACK_CAMERAS
from cblrs.locate import ColorLocator, HomographyLocator, Locator, LUTLocator
from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference


def bounds_of(plane: PlaneSpec) -> tuple[float, float, float, float]:
    x0, y0 = plane.origin
    return x0, y0, x0 + plane.width, y0 + plane.length


@pytest.mark.parametrize("view", range(7), ids=WILDTRACK_CAMERAS)
def test_three_localisers_agree_on_wildtrack(view, wildtrack_cameras, wildtrack_references):
    camera, reference = wildtrack_cameras[view], wildtrack_references[view]
    plane = wildtrack_plane(16)
    locators = {
        "homography": HomographyLocator.from_camera(camera, bounds=bounds_of(plane)),
        "lut": LUTLocator.from_camera(camera, bounds=bounds_of(plane)),
        "lut_from_reference": LUTLocator.from_reference(reference),
        "colour": ColorLocator(reference),
    }
    generator = np.random.default_rng(view)
    pixels = generator.uniform([-0.5, -0.5], [1919.49, 1079.49], size=(4000, 2))
    results = {name: locator.locate(pixels) for name, locator in locators.items()}
    valid = np.logical_and.reduce([valid for _, valid in results.values()])
    assert valid.sum() > 1500  # most of the sampled image sees the ground area
    # Which pixels are valid agrees except within a pixel of the plane's outline.
    for name, (_, name_valid) in results.items():
        assert (name_valid != valid).mean() < 0.01, name
    step = np.array(plane.step)
    exact = results["homography"][0][valid]
    # The LUT holds each pixel centre's exact position, the colour its cell centre: compare
    # them at the pixel centres the lookups use.
    centres = np.floor(pixels[valid] + 0.5)
    exact_at_centres, _ = locators["homography"].locate(centres)
    for name in ("lut", "lut_from_reference", "colour"):
        error = np.abs(results[name][0][valid] - exact_at_centres) / step
        assert error.max() <= 1.0, (name, error.max(axis=0))
    # ... and within the distance a pixel spans of the unrounded homography position.
    assert np.all(np.isfinite(exact))


@pytest.mark.parametrize("view", [0, 4])
def test_one_point_path_matches_batched_path(view, wildtrack_cameras, wildtrack_references):
    camera, reference = wildtrack_cameras[view], wildtrack_references[view]
    plane = wildtrack_plane(16)
    generator = np.random.default_rng(11)
    pixels = generator.uniform([-3, -3], [1923, 1083], size=(300, 2))
    for locator in (
        HomographyLocator.from_camera(camera, bounds=bounds_of(plane)),
        LUTLocator.from_camera(camera, bounds=bounds_of(plane)),
        ColorLocator(reference),
    ):
        assert isinstance(locator, Locator)
        world_xy, valid = locator.locate(pixels)
        for index, (x, y) in enumerate(pixels):
            one = locator.locate_one(float(x), float(y))
            assert (one is not None) == valid[index], (type(locator).__name__, x, y)
            if one is not None:
                np.testing.assert_allclose(one, world_xy[index], rtol=1e-6, atol=1e-6)


@pytest.fixture(scope="module")
def horizon_locators():
    """A camera with the horizon at row ~73 and a plane far wider than what it sees."""
    camera = posed_camera()
    plane = PlaneSpec(1, (-5000.0, -5000.0), 10000.0, 10000.0, bits=16)
    reference = render_reference(camera, plane)
    return camera, {
        "homography": HomographyLocator.from_camera(camera),
        "lut": LUTLocator.from_camera(camera),
        "colour": ColorLocator(reference),
    }


ABOVE_HORIZON = np.array([[0.0, 0.0], [320.0, 10.0], [639.0, 50.0], [100.0, 72.0]])
BELOW_HORIZON = np.array([[320.0, 359.0], [0.0, 200.0]])


@pytest.mark.parametrize("name", ["homography", "lut", "colour", "camera"])
def test_pixels_above_the_horizon_are_invalid(horizon_locators, name):
    camera, locators = horizon_locators
    locate = camera.pixel_to_world if name == "camera" else locators[name].locate
    world_xy, valid = locate(ABOVE_HORIZON)
    assert not valid.any()
    assert np.isnan(world_xy).all()
    below_xy, below_valid = locate(BELOW_HORIZON)
    assert below_valid.all()
    assert np.isfinite(below_xy).all()
    if name != "camera":
        for x, y in ABOVE_HORIZON:
            assert locators[name].locate_one(x, y) is None


@pytest.mark.parametrize(
    "pixel",
    [(-0.7, 200.0), (640.0, 200.0), (320.0, -0.51), (320.0, 359.6), (np.nan, 200.0)],
)
def test_pixels_outside_the_image_are_invalid(horizon_locators, pixel):
    _, locators = horizon_locators
    for name, locator in locators.items():
        _, valid = locator.locate(np.array([pixel]))
        assert not valid[0], name
        assert locator.locate_one(*pixel) is None, name


@pytest.mark.parametrize("name", ["homography", "lut", "colour"])
def test_empty_and_malformed_input(horizon_locators, name):
    _, locators = horizon_locators
    world_xy, valid = locators[name].locate(np.zeros((0, 2)))
    assert world_xy.shape == (0, 2) and valid.shape == (0,)
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        locators[name].locate(np.zeros((3, 3)))


def test_lut_save_and_load(tmp_path, horizon_locators):
    _, locators = horizon_locators
    path = locators["lut"].save(tmp_path / "table.npy")
    loaded = LUTLocator.load(path)
    np.testing.assert_array_equal(loaded.table, locators["lut"].table)
    (tmp_path / "bad.npy").write_bytes(b"nonsense")
    with pytest.raises(Exception, match="cannot read LUT"):
        LUTLocator.load(tmp_path / "bad.npy")
