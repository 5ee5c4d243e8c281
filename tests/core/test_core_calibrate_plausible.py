"""Implausible calibrations are refused with the likely mistake named (issue 21, item 5).

The documentation's clicked points (``gate.csv``) written as a newcomer got them wrong: ground
positions in centimetres or millimetres, map pixels read as metres, ``u, v`` or ``x, y``
columns swapped. Each fits with a small pixel error, so before this check each exited 0
("camera 598 m high", a generic warning); now each is one sentence and exit 1, and the
options that say "this really is so" (``--left-handed``, ``--max-height-m``) let a real
left-handed world or a very high camera through.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml

from cblrs.calibrate import Correspondences, calibrate_camera
from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.errors import CalibrationError

# docs/sites.md's example points (pixels, metres) of a 1280x720 camera about 6 m high.
GATE = [
    (1099.9, 288.4, 16, 0, "bench"),
    (16.1, 271.4, 4, 18, "bin"),
    (521.4, 599.9, 2, 2, "lamp"),
    (608.1, 126.2, 26, 20, "drain"),
    (343.0, 329.3, 6, 10, "bollard"),
    (807.5, 402.0, 8, 2, "tree"),
    (122.1, 554.6, 0, 6, "sign"),
    (877.7, 146.8, 28, 10, "gate post"),
]


def write_points(path, rows) -> str:
    path.write_text("u,v,x,y,name\n" + "".join(",".join(map(str, row)) + "\n" for row in rows))
    return str(path)


def run(capsys, *arguments) -> tuple[int, str, str]:
    code = main(["calibrate", *arguments])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_the_readme_points_calibrate(tmp_path, capsys):
    code, out, err = run(capsys, write_points(tmp_path / "gate.csv", GATE), "--image-size",
                         "1280x720")
    assert code == 0, err
    assert re.search(r"camera at \(-4\.\d\d, -3\.\d\d\) m, 5\.\d\d m high", out), out


@pytest.mark.parametrize(
    ("name", "transform", "size", "message"),
    [
        (
            "centimetres",
            lambda u, v, x, y, n: (u, v, x * 100, y * 100, n),
            "1280x720",
            r"^gate\.csv: the fit puts the camera 59\d\.\d m high: are x and y in centimetres\? "
            r"They must be metres \(divided by 100 the camera is 5\.9\d m high\), or map pixels "
            r"with --world map\. A camera really higher than 100 m: raise --max-height-m \(in a "
            r"site file max_height_m\)\.$",
        ),
        (
            "millimetres",
            lambda u, v, x, y, n: (u, v, x * 1000, y * 1000, n),
            "1280x720",
            r"are x and y in millimetres\? They must be metres \(divided by 1000 the camera is "
            r"5\.9\d m high\)",
        ),
        (
            "u and v swapped",
            lambda u, v, x, y, n: (v, u, x, y, n),
            "1280x720",
            r"^gate\.csv: bench \(u, v = 288\.4, 1099\.9\) lies outside the 1280x720 image \(3 of "
            r"8 points do\); u and v look swapped",
        ),
        (
            "u and v swapped on a square frame",
            lambda u, v, x, y, n: (v, u, x, y, n),
            "1280x1280",
            r"^gate\.csv: the points show the ground mirrored .*: are u and v, or x and y, "
            r"swapped, .*--left-handed",
        ),
        (
            "x and y swapped",
            lambda u, v, x, y, n: (u, v, y, x, n),
            "1280x720",
            r"^gate\.csv: the points show the ground mirrored \(a camera seeing them would stand "
            r"below the ground\): are u and v, or x and y, swapped, or are x, y map pixels",
        ),
        (
            "the wrong image size",
            lambda u, v, x, y, n: (u, v, x, y, n),
            "640x360",
            r"lies outside the 640x360 image .*; check the image size and that u is pixels "
            r"from the left, v from the top\.$",
        ),
    ],
)
def test_implausible_points_are_refused_naming_the_mistake(tmp_path, capsys, name, transform,
                                                           size, message):
    rows = [transform(*row) for row in GATE]
    code, out, err = run(capsys, write_points(tmp_path / "gate.csv", rows), "--image-size",
                         size, "--out", str(tmp_path / "gate.json"))
    assert code == 1, (name, out)
    sentence = err.removeprefix("cblrs calibrate: error: ").strip()
    assert "\n" not in sentence and "Traceback" not in err
    assert re.search(message, sentence), sentence
    assert not (tmp_path / "gate.json").exists()  # nothing written


def test_map_pixels_read_as_metres_are_refused(tmp_path, capsys):
    # The site plan at 0.05 m per pixel, origin at map pixel (120, 880), y up: the newcomer
    # forgot --world map.
    rows = [(u, v, 120 + x / 0.05, 880 - y / 0.05, n) for u, v, x, y, n in GATE]
    code, _, err = run(capsys, write_points(tmp_path / "gate.csv", rows), "--image-size",
                       "1280x720")
    assert code == 1
    assert "are x, y map pixels (y growing down the map: use --world map)?" in err
    code, out, err = run(capsys, str(tmp_path / "gate.csv"), "--image-size", "1280x720",
                         "--world", "map", "--metres-per-pixel", "0.05", "--map-origin",
                         "120,880")
    assert code == 0, err
    assert re.search(r"5\.\d\d m high", out)


def test_a_left_handed_world_passes_when_said_so(tmp_path, capsys):
    rows = [(u, v, y, x, n) for u, v, x, y, n in GATE]
    code, out, err = run(capsys, write_points(tmp_path / "gate.csv", rows), "--image-size",
                         "1280x720", "--left-handed")
    assert code == 0, err
    assert "model homography" in out and "camera position unknown" in out


def test_a_really_high_camera_passes_when_said_so(tmp_path, capsys):
    high = Camera.from_pose("mast", (-60.0, -60.0, 150.0), 45, 35, 2400, (1280, 720))
    grid = np.array([(x, y) for x in range(0, 200, 20) for y in range(0, 200, 20)], float)
    pixels, valid = high.world_to_pixel(grid)
    inside = valid & np.all((pixels > 20) & (pixels < (1260, 700)), axis=1)
    rows = [(u, v, x, y, f"p{index}") for index, ((u, v), (x, y)) in
            enumerate(zip(pixels[inside], grid[inside], strict=True))]
    assert len(rows) >= 8
    path = write_points(tmp_path / "mast.csv", rows)
    code, _, err = run(capsys, path, "--image-size", "1280x720")
    assert code == 1 and "the fit puts the camera 150.0 m high" in err
    code, out, err = run(capsys, path, "--image-size", "1280x720", "--max-height-m", "200")
    assert code == 0, err
    assert "150.00 m high" in out


def test_points_spanning_kilometres_without_a_position_are_refused():
    # Four points fit a homography exactly; the camera looks straight down, so no position can
    # be read from it: the spread of the points is what gives the centimetres away.
    down = Camera.from_pose("down", (10.0, 10.0, 8.0), 0, 90, 1000, (1280, 720))
    pixels = np.array([[200.0, 150.0], [1100.0, 180.0], [1050.0, 600.0], [250.0, 650.0]])
    world, _ = down.pixel_to_world(pixels)
    fit = calibrate_camera(Correspondences(pixels, world, source="down.csv"), (1280, 720))
    assert fit.position is None
    with pytest.raises(CalibrationError, match=r"the points span .* m: .*centimetres"):
        calibrate_camera(Correspondences(pixels, world * 1000, source="down.csv"), (1280, 720))


def test_a_site_file_with_centimetres_is_refused_and_its_keys_let_through(tmp_path, capsys):
    site = {
        "version": 1,
        "planes": [{"id": 1, "origin": [-5, -5], "size": [40, 30]}],
        "cameras": [{
            "name": "gate",
            "image_size": [1280, 720],
            "points": [[u, v, y, x, n] for u, v, x, y, n in GATE],
        }],
    }
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(site))
    assert main(["render", "--site", str(path), "--out", str(tmp_path / "refs")]) == 1
    err = capsys.readouterr().err
    assert "mirrored" in err and "left_handed: true" in err and "Traceback" not in err
    site["cameras"][0]["left_handed"] = True
    path.write_text(yaml.safe_dump(site))
    assert main(["render", "--site", str(path), "--out", str(tmp_path / "refs")]) == 0
