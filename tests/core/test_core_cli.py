"""The render, locate and show subcommands, run through cblrs.cli.main.main."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from core_cameras import posed_camera

from cblrs.calibration import camera_to_dict
from cblrs.cli.main import main
from cblrs.reference import ReferenceImage


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(arg) for arg in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line_error(code: int, err: str, message: str) -> None:
    assert code != 0
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert message in err, err


@pytest.fixture(scope="module")
def wildtrack_render(wildtrack_root, tmp_path_factory):
    """`cblrs render WILDTRACK --bits 8 --json`, run once for the module."""
    out = tmp_path_factory.mktemp("references")
    code = main(["render", str(wildtrack_root), "--out", str(out), "--bits", "8", "--json"])
    assert code == 0
    return out


def test_render_wildtrack_writes_seven_references(wildtrack_render):
    paths = sorted(wildtrack_render.glob("*.png"))
    assert [path.stem for path in paths] == sorted(
        ["CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3"]
    )
    reference = ReferenceImage.load(paths[0], expected_size=(1920, 1080))
    assert reference.bits == 8
    # The annotated area (-3, -9, 12 x 36 m) grown by the loader's 2 m margin, as `cblrs track`.
    assert reference.planes[0].origin == (-5.0, -11.0)
    assert (reference.planes[0].width, reference.planes[0].length) == (16.0, 40.0)
    assert 0.5 < reference.coverage() < 0.95


def test_render_table_and_json(tmp_path, capsys):
    camera_file = tmp_path / "cameras.json"
    camera_file.write_text(json.dumps({"cameras": [camera_to_dict(posed_camera())]}))
    out = tmp_path / "out"
    code, stdout, _ = run(
        capsys,
        "render",
        camera_file,
        "--out",
        out,
        "--plane",
        "-10,-5,20,40",
        "--plane",
        "-1,2,2,1,1.0",
        "--preview",
        "--quiet",
    )
    assert code == 0
    assert "synthetic" in stdout and "coverage %" in stdout
    assert (out / "synthetic.png").is_file() and (out / "synthetic_preview.png").is_file()
    reference = ReferenceImage.load(out / "synthetic.png")
    assert reference.planes.ids == [1, 2] and reference.planes[1].height == 1.0
    assert set(np.unique(reference.pixels[..., 2]).tolist()) == {0, 1, 2}
    code, stdout, _ = run(
        capsys,
        "render",
        camera_file,
        "--out",
        out,
        "--plane",
        "-10,-5,20,40",
        "--bits",
        "8",
        "--json",
    )
    result = json.loads(stdout)
    assert code == 0 and result["bits"] == 8
    assert result["cameras"][0]["camera"] == "synthetic"
    assert 0 < result["cameras"][0]["coverage"] < 1


def test_render_planes_file(tmp_path, capsys):
    camera_file = tmp_path / "camera.json"
    camera_file.write_text(json.dumps(camera_to_dict(posed_camera())))
    planes_file = tmp_path / "planes.json"
    planes_file.write_text(
        json.dumps({"planes": [{"plane_id": 5, "origin": [-10, -5], "width": 20, "length": 40}]})
    )
    code, _, _ = run(
        capsys,
        "render",
        camera_file,
        "--out",
        tmp_path,
        "--planes-file",
        planes_file,
        "--bits",
        "8",
        "--quiet",
    )
    assert code == 0
    reference = ReferenceImage.load(tmp_path / "synthetic.png")
    assert reference.planes.ids == [5] and reference.bits == 8


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "give the plane extent with --plane"),
        (["--plane", "1,2,3"], "needs 4 or 5 numbers"),
        (["--plane", "a,b,c,d"], "must be numbers"),
        (["--plane", "0,0,-1,5"], "width and length must be positive"),
        (["--plane", "0,0,5,5", "--plane", "0,0,5,5", "--bits", "8"], ""),  # fine: two ids
    ],
)
def test_render_plane_errors(tmp_path, capsys, extra, message):
    camera_file = tmp_path / "camera.json"
    camera_file.write_text(json.dumps(camera_to_dict(posed_camera())))
    code, _, err = run(capsys, "render", camera_file, "--out", tmp_path / "o", "--quiet", *extra)
    if message:
        assert_one_line_error(code, err, message)
    else:
        assert code == 0


def test_render_missing_calibration(tmp_path, capsys):
    code, _, err = run(capsys, "render", tmp_path / "nothing", "--out", tmp_path)
    assert_one_line_error(code, err, "does not exist")


def test_locate_dataset_frame(wildtrack_root, wildtrack_render, capsys):
    reference = wildtrack_render / "CVLab1.png"
    code, stdout, _ = run(
        capsys, "locate", reference, "--dataset", wildtrack_root, "--frame", "0", "--json"
    )
    assert code == 0
    result = json.loads(stdout)
    summary = result["summary"]
    print(f"\ncblrs locate CVLab1 frame 0 (8-bit): {summary}")
    assert summary["people"] >= 20
    assert summary["median_error_m"] < 0.5
    assert summary["share_within_0_5_m"] > 0.5
    code, stdout, _ = run(capsys, "locate", reference, "--dataset", wildtrack_root, "--frame", 5)
    assert code == 0 and "median error" in stdout


def test_locate_pixels_and_boxes(wildtrack_render, tmp_path, capsys):
    reference = wildtrack_render / "IDIAP2.png"
    code, stdout, _ = run(capsys, "locate", reference, "--pixels", "960,1000; 5,5", "--json")
    assert code == 0
    rows = json.loads(stdout)["positions"]
    assert [row["valid"] for row in rows] == [True, False]
    assert rows[1]["x"] is None
    boxes = tmp_path / "boxes.txt"
    boxes.write_text(
        "# x_min y_min x_max y_max class\n900 700 1000 1000 person\n\n10,10,50,60  # comment\n"
    )
    code, stdout, _ = run(capsys, "locate", reference, "--boxes", boxes, "--vtp", "0.9")
    assert code == 0
    lines = stdout.strip().splitlines()
    assert "class" in lines[0] and "person" in lines[2] and len(lines) == 4
    # Same answer as --pixels at the target point (x = 950, y = 700 + 0.9 * 300 = 970).
    _, direct, _ = run(capsys, "locate", reference, "--pixels", "950,970", "--json")
    code, via_boxes, _ = run(
        capsys, "locate", reference, "--boxes", boxes, "--vtp", "0.9", "--json"
    )
    assert json.loads(via_boxes)["positions"][0]["x"] == json.loads(direct)["positions"][0]["x"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--pixels", "1;2"], "must be two finite numbers x,y"),
        (["--pixels", "1,x"], "is not a pair of numbers"),
        (["--pixels", ";"], "holds no pixel"),
        (["--pixels", "1,1", "--vtp", "1.5"], "--vtp must be within 0..1"),
        (["--dataset", "{root}"], "--dataset needs --frame"),
        (["--dataset", "{root}", "--frame", "3"], "WILDTRACK frame 3 is not annotated"),
        (["--boxes", "{missing}"], "does not exist"),
    ],
)
def test_locate_errors(wildtrack_root, wildtrack_render, tmp_path, capsys, extra, message):
    extra = [value.format(root=wildtrack_root, missing=tmp_path / "none.txt") for value in extra]
    code, _, err = run(capsys, "locate", wildtrack_render / "CVLab2.png", *extra)
    assert_one_line_error(code, err, message)


def test_locate_bad_boxes_file_and_non_wildtrack_reference(wildtrack_root, tmp_path, capsys):
    camera_file = tmp_path / "camera.json"
    camera_file.write_text(json.dumps(camera_to_dict(posed_camera())))
    run(capsys, "render", camera_file, "--out", tmp_path, "--plane", "-10,-5,20,40", "--quiet")
    reference = tmp_path / "synthetic.png"
    code, _, err = run(capsys, "locate", reference, "--dataset", wildtrack_root, "--frame", 0)
    assert_one_line_error(code, err, "is not a WILDTRACK camera")
    boxes = tmp_path / "boxes.txt"
    boxes.write_text("1 2 3\n")
    code, _, err = run(capsys, "locate", reference, "--boxes", boxes)
    assert_one_line_error(code, err, "boxes.txt:1: expected 'x_min y_min x_max y_max [class]'")
    code, _, err = run(capsys, "locate", boxes, "--pixels", "1,1")
    assert_one_line_error(code, err, "is not a PNG file")


def test_show_blank_and_over_a_frame(wildtrack_render, tmp_path, capsys):
    reference = wildtrack_render / "CVLab3.png"
    out = tmp_path / "shown.png"
    code, stdout, _ = run(capsys, "show", reference, "--out", out, "--json")
    assert code == 0 and json.loads(stdout)["camera"] == "CVLab3"
    image = cv2.imread(str(out))
    assert image.shape == (1080, 1920, 3)
    assert image[:50].max() == 0  # the sky above the ground area stays black
    assert image[600:].std() > 20  # colours and grid below
    frame = np.full((1080, 1920, 3), 128, dtype=np.uint8)
    frame_path = tmp_path / "frame.jpg"
    cv2.imwrite(str(frame_path), frame)
    code, _, _ = run(capsys, "show", reference, "--out", out, "--frame", frame_path, "--grid", 2)
    assert code == 0
    over = cv2.imread(str(out))
    assert abs(int(over[20, 20, 0]) - 128) <= 2  # frame shows through where no plane is


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--frame", "{small}"], "but the reference is 1920x1080"),
        (["--frame", "{missing}"], "does not exist"),
        (["--frame", "{text}"], "is not an image OpenCV can read"),
        (["--grid", "-1"], "--grid must be a non-negative number"),
        (["--out", "{dir}/x.jpg"], "--out must be a .png file"),
    ],
)
def test_show_errors(wildtrack_render, tmp_path, capsys, extra, message):
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 10, 3), dtype=np.uint8))
    text = tmp_path / "text.png"
    text.write_text("not an image")
    extra = [
        value.format(small=small, missing=tmp_path / "no.png", text=text, dir=tmp_path)
        for value in extra
    ]
    argv = ["show", wildtrack_render / "IDIAP1.png"]
    if "--out" not in extra:
        argv += ["--out", tmp_path / "o.png"]
    code, _, err = run(capsys, *argv, *extra)
    assert_one_line_error(code, err, message)


def test_render_distorted_wildtrack(wildtrack_root, wildtrack_render, tmp_path, capsys):
    code, stdout, _ = run(
        capsys,
        "render",
        wildtrack_root,
        "--out",
        tmp_path,
        "--bits",
        "8",
        "--distorted",
        "--json",
    )
    assert code == 0
    result = json.loads(stdout)
    assert result["distorted"] is True and len(result["cameras"]) == 7
    raw = ReferenceImage.load(tmp_path / "CVLab1.png")
    undistorted = ReferenceImage.load(wildtrack_render / "CVLab1.png")
    # The lens moves the picture by many pixels: the two references differ widely.
    assert (raw.pixels != undistorted.pixels).any(axis=2).mean() > 0.3
