"""``cblrs demo``'s live part: the plaza's cameras replayed through ``cblrs up`` (tracks on
the live map, stopped by --live-seconds), never without a terminal unless asked, and the site
file it writes (the scene's cameras, plane and boxes, played back and forth)."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from up_helpers import ENVIRONMENT, first_tracks_on_the_map

from cblrs.cli.main import main
from cblrs.datasets.presets import make_scene
from cblrs.site import load_site
from cblrs.up.backbone import choose_backbone
from cblrs.up.scene_site import ping_pong, write_scene_site

DEMO = [sys.executable, "-m", "cblrs.cli.main", "demo"]


@pytest.mark.parametrize(("count", "total", "expected"), [
    (3, 7, [0, 1, 2, 1, 0, 1, 2]),
    (2, 5, [0, 1, 0, 1, 0]),
    (1, 3, [0, 0, 0]),
    (4, 2, [0, 1]),
    (3, 0, []),
])
def test_ping_pong_plays_the_frames_back_and_forth(count, total, expected):
    assert ping_pong(count, total).tolist() == expected


def test_the_live_site_is_the_scenes_cameras_plane_and_people(tmp_path):
    scene = make_scene("plaza", duration_s=4)
    path = write_scene_site(scene, tmp_path / "live", replay_s=10)
    site = load_site(path)
    assert [spec.name for spec in site.model.cameras] == scene.camera_names
    assert site.planes.ids == [scene.plane.plane_id]
    fps = 1 / scene.frame_interval
    frames = round(10 * fps)
    for index, spec in enumerate(site.model.cameras):
        assert spec.source.kind == "detections" and spec.source.fps == pytest.approx(fps)
        rows = np.loadtxt(tmp_path / "live" / spec.source.path, delimiter=",", ndmin=2)
        # the people of each played frame, in the ping-pong order; the cars left out
        order = ping_pong(len(scene.frames), frames)
        expected = sum(int(np.sum(scene.detections[position][index].class_id == 0))
                       for position in order)
        assert len(rows) == expected > 0
        assert rows[:, 0].min() >= 1 and rows[:, 0].max() <= frames
        # the site's camera is the scene's: the same pixel of the same ground point
        point = np.array([[1.0, 2.0]])
        np.testing.assert_allclose(site.camera(spec.name).camera.world_to_pixel(point)[0],
                                   scene.cameras[index].world_to_pixel(point)[0], atol=1e-6)


def test_without_a_terminal_the_demo_does_not_go_live(tmp_path):
    result = subprocess.run([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                             str(tmp_path / "demo"), "--quiet"], capture_output=True,
                            text=True, timeout=300, stdin=subprocess.DEVNULL, env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "demo" / "live").exists()
    assert "dashboard:" not in result.stdout


@pytest.mark.parametrize("extra", [["--json"], ["--no-live"], ["--dataset", "x"]])
def test_live_seconds_with_an_option_that_excludes_it_is_one_sentence(tmp_path, capsys,
                                                                      extra):
    code = main(["demo", "--out", str(tmp_path), "--live-seconds", "5", *extra])
    assert code == 2
    assert "--live-seconds goes without --no-live, --json and --dataset" in (
        capsys.readouterr().err)


def test_the_demo_goes_live_tracks_reach_the_map_and_it_stops_after_live_seconds(tmp_path):
    try:
        backbone = choose_backbone()
    except Exception as error:
        pytest.skip(f"no broker: {error}")
    out = tmp_path / "demo"
    started = time.monotonic()
    process = subprocess.Popen([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                                str(out), "--live-seconds", "150"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=ENVIRONMENT)
    try:
        line = process.stdout.readline()
        while line and not line.startswith("dashboard: "):
            line = process.stdout.readline()
        assert line, process.communicate()[1]
        assert "/login?token=" in line
        rows = first_tracks_on_the_map(line.split(" ", 1)[1].strip(), timeout=90)
        on_the_map_s = time.monotonic() - started
        process.send_signal(2)  # Ctrl-C stops it before --live-seconds
        stdout, stderr = process.communicate(timeout=90)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert rows and all(len(row) == 4 for row in rows), rows
    assert process.returncode == 0, stderr
    assert "SIGINT: stopping cameras, matchers, dashboard, broker" in stdout
    state = json.loads((out / "live" / "state" / "up.json").read_text())
    assert state["backbone"] == backbone.kind
    assert (out / "roundabout" / "metrics.json").is_file()  # the offline part ran first
    print(f"demo: tracks on the live map {on_the_map_s:.1f} s after cblrs demo started "
          f"({backbone.kind})")


def test_live_seconds_stops_the_site_by_itself(tmp_path):
    try:
        choose_backbone()
    except Exception as error:
        pytest.skip(f"no broker: {error}")
    out = tmp_path / "demo"
    result = subprocess.run([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                             str(out), "--live-seconds", "3", "--quiet"], capture_output=True,
                            text=True, timeout=300, env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    assert "dashboard: http://127.0.0.1:" in result.stdout
    assert (out / "live" / "state" / "plane1.db").is_file()
