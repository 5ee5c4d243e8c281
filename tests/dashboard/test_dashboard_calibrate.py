"""The calibration page in a real browser: click pairs on a real MultiviewX frame and the map.

The site is `cblrs site init` of MultiviewX with Camera1's real frame; an admin logs in
through the login form (the calibration page is theirs), then the test clicks eight
ground points in the frame (where the published calibration sees them) and the same points on
the map, as an operator would, and checks that the fit appears with small errors, that
fewer than four pairs give none, and that saving writes the pairs into the site file (the
previous file kept), renders Camera1's reference and shows it. MultiviewX's world (from Unity)
is left-handed: its points are refused as mirrored until the page is told so.

A second test zooms into the frame with the mouse wheel (one screen pixel finer than an image
pixel), pans by dragging, and types the ground points instead of clicking them.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from dashboard_helpers import ADMIN, login, open_login_link, wait_until

from cblrs.cli.main import main
from cblrs.reference import ReferenceImage
from cblrs.site import load_site

CAMERA = "Camera1"


def spread_points(camera, count: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``count`` ground points of the annotated area that the camera sees well inside its
    frame, spread out (each the farthest from those chosen), and their pixels."""
    grid = np.array([(x, y) for x in np.arange(0.5, 25.0, 1.0) for y in np.arange(0.5, 16.0, 1.0)])
    pixels, valid = camera.world_to_pixel(grid)
    width, height = camera.image_size
    inside = valid & (pixels[:, 0] > 60) & (pixels[:, 0] < width - 60) \
        & (pixels[:, 1] > 60) & (pixels[:, 1] < height - 60)
    grid, pixels = grid[inside], pixels[inside]
    chosen = [0]
    while len(chosen) < count:
        distance = np.min(np.hypot(*(pixels[:, None, :] - pixels[chosen][None]).transpose(2, 0, 1)),
                          axis=1)
        chosen.append(int(np.argmax(distance)))
    return grid[chosen], pixels[chosen]


@pytest.fixture
def multiviewx_site(multiviewx_real_root, tmp_path):
    path = tmp_path / "site.yaml"
    assert main(["site", "init", str(multiviewx_real_root), "--out", str(path)]) == 0
    document = yaml.safe_load(path.read_text())
    frame = multiviewx_real_root / "Image_subsets" / "C1" / "0000.jpg"
    document["cameras"][0]["frame"] = str(frame)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def test_calibration_page_fits_saves_and_renders(multiviewx_site, start_dashboard, users_file,
                                                 page, tmp_path):
    site = load_site(multiviewx_site)
    truth = site.camera(CAMERA).camera
    ground, pixels = spread_points(truth)
    width, height = truth.image_size
    pairs = list(zip(pixels.tolist(), ground.tolist(), strict=True))
    references = tmp_path / "references"
    url = start_dashboard("--site", str(multiviewx_site), "--references", str(references),
                          "--users", str(users_file)).url
    login(page, url, ADMIN, f"calibrate?camera={CAMERA}")
    wait_until(lambda: page.evaluate("window.cblrsCalibrate.ready && "
                                     "window.cblrsCalibrate.frameLoaded === true"), 20,
               "the page and Camera1's frame")

    def click_pair(pixel, world) -> None:
        x, y = page.evaluate(f"window.cblrsCalibrate.frameToScreen({pixel[0]}, {pixel[1]})")
        page.mouse.click(x, y)
        x, y = page.evaluate(f"window.cblrsCalibrate.worldToScreen({world[0]}, {world[1]})")
        page.mouse.click(x, y)

    for pixel, world in pairs[:3]:
        click_pair(pixel, world)
    assert "four or more" in page.inner_text("#summary")
    for pixel, world in pairs[3:]:
        click_pair(pixel, world)
    # The ground seen mirrored: refused, naming swapped columns, until the world is said to be
    # left-handed.
    wait_until(lambda: "mirrored" in page.inner_text("#summary"), 30, "the mirrored refusal")
    assert "u and v, or x and y, swapped," in page.inner_text("#summary")
    assert page.is_disabled("#save")
    page.check("#left-handed")
    wait_until(lambda: page.evaluate("(window.cblrsCalibrate.result || {}).points") == 8, 30,
               "the fit of eight pairs")
    result = page.evaluate("window.cblrsCalibrate.result")
    assert result["points"] == 8 and result["model"] in ("k1", "focal", "pose", "homography")
    # Clicks land within a canvas pixel: about a frame pixel in the image, centimetres on
    # the map; the fitted camera reprojects them within a few pixels.
    assert result["rms_px"] < 6.0, result
    assert result["median_error_m"] < 0.15, result
    assert page.locator("#pairs tbody tr").count() == 8
    assert "RMS" in page.inner_text("#summary")

    page.click("#save")
    wait_until(lambda: page.evaluate("window.cblrsCalibrate.referenceLoaded === true"), 60,
               "the saved reference's preview")
    saved = load_site(multiviewx_site)
    spec = saved.model.cameras[0]
    assert spec.name == CAMERA and spec.geometry == "points" and len(spec.points) == 8
    assert spec.left_handed
    assert (multiviewx_site.parent / "site.yaml.bak").is_file()
    reference = ReferenceImage.load(references / f"{CAMERA}.png")
    assert reference.image_size == (width, height)
    # The clicked camera sees the ground where the published calibration does.
    located, ok = saved.camera(CAMERA).camera.pixel_to_world(pixels)
    assert ok.all()
    assert np.median(np.hypot(*(located - ground).T)) < 0.15
    assert page.evaluate("document.getElementById('reference').naturalWidth") == width
    page.screenshot(path=str(tmp_path / "calibrate.png"))


def test_calibration_page_zooms_pans_and_takes_typed_ground_points(multiviewx_site,
                                                                    start_dashboard, page):
    truth = load_site(multiviewx_site).camera(CAMERA).camera
    ground, pixels = spread_points(truth)
    served = start_dashboard("--site", str(multiviewx_site))
    open_login_link(page, served.link)  # no --users: the run's login link makes this page an admin
    url = served.url
    page.goto(f"{url}calibrate?camera={CAMERA}")
    wait_until(lambda: page.evaluate("window.cblrsCalibrate.ready && "
                                     "window.cblrsCalibrate.frameLoaded === true"), 20,
               "the page and Camera1's frame")
    page.check("#left-handed")
    whole = page.evaluate("window.cblrsCalibrate.imagePixelsPerScreenPixel()")
    assert whole > 1.0  # the whole 1920x1080 frame in a half-page pane: clicks miss pixels

    # Zoom in on the first point with the wheel: the image point under the mouse stays there
    # (the browser puts the mouse on whole CSS pixels).
    x, y = (round(value) for value in page.evaluate(
        f"window.cblrsCalibrate.frameToScreen({pixels[0][0]}, {pixels[0][1]})"))
    under = page.evaluate(f"window.cblrsCalibrate.screenToFrame({x}, {y})")
    page.mouse.move(x, y)
    for _ in range(12):
        page.mouse.wheel(0, -100)
    wait_until(lambda: page.evaluate("window.cblrsCalibrate.imagePixelsPerScreenPixel()")
               < whole / 10, 10, "the zoomed-in frame")
    zoomed = page.evaluate("window.cblrsCalibrate.imagePixelsPerScreenPixel()")
    assert zoomed < 0.5
    assert f"{zoomed:.2f} image px" in page.inner_text("#frame-zoom")
    np.testing.assert_allclose(page.evaluate(f"window.cblrsCalibrate.screenToFrame({x}, {y})"),
                               under, atol=1e-6)

    # A drag pans (and places no point); a click then lands within a fraction of a pixel.
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 40, y + 25, steps=5)
    page.mouse.up()
    assert page.evaluate("window.cblrsCalibrate.pendingPixel") is None
    u, v = page.evaluate(f"window.cblrsCalibrate.screenToFrame({x}, {y})")
    np.testing.assert_allclose((u, v), (under[0] - 40 * zoomed, under[1] - 25 * zoomed),
                               atol=1e-6)

    def place(pixel, world) -> None:
        # Bring the pixel into view at this zoom (reset, then zoom on it), click it, type
        # its ground position.
        page.click("#frame-fit")
        sx, sy = page.evaluate(f"window.cblrsCalibrate.frameToScreen({pixel[0]}, {pixel[1]})")
        page.mouse.move(sx, sy)
        for _ in range(12):
            page.mouse.wheel(0, -100)
        wait_until(lambda: page.evaluate("window.cblrsCalibrate.frameView.zoom") > 10, 10,
                   "the zoom")
        sx, sy = page.evaluate(f"window.cblrsCalibrate.frameToScreen({pixel[0]}, {pixel[1]})")
        page.mouse.click(sx, sy)
        page.fill("#typed-x", repr(float(world[0])))
        page.fill("#typed-y", repr(float(world[1])))
        page.click("#typed-set")

    for pixel, world in zip(pixels.tolist(), ground.tolist(), strict=True):
        place(pixel, world)
    wait_until(lambda: page.evaluate("(window.cblrsCalibrate.result || {}).points") == 8, 30,
               "the fit of eight typed pairs")
    pairs = page.evaluate("window.cblrsCalibrate.pairs")
    typed = np.array([[pair["x"], pair["y"]] for pair in pairs])
    clicked = np.array([[pair["u"], pair["v"]] for pair in pairs])
    np.testing.assert_array_equal(typed, ground)  # typed: exact
    assert np.abs(clicked - pixels).max() < 0.5  # clicked zoomed in: under half a pixel
    result = page.evaluate("window.cblrsCalibrate.result")
    # With exact ground points and sub-pixel clicks the fit is far tighter than clicking
    # both at the whole-frame zoom (test above: under 6 px, 0.15 m).
    assert result["rms_px"] < 1.0, result
    assert result["median_error_m"] < 0.02, result

    # A typed correction in the table refits.
    fits = page.evaluate("window.cblrsCalibrate.fits")
    page.fill("#pairs input[data-pair='0'][data-key='x']", repr(float(ground[0][0]) + 2.0))
    page.press("#pairs input[data-pair='0'][data-key='x']", "Enter")
    wait_until(lambda: page.evaluate("window.cblrsCalibrate.fits") > fits, 30, "the refit")
    assert page.evaluate("window.cblrsCalibrate.pairs[0].x") == float(ground[0][0]) + 2.0
