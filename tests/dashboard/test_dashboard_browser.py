"""The dashboard in a real browser (headless Chromium), fed by a real matcher.

A Mosquitto with users and an ACL; `cblrs matcher --site` counting the WILDTRACK site's
lines and zones; seven camera nodes replaying 60 s of WILDTRACK at ~5x; `cblrs dashboard`
logged in to the broker as the read-only viewer, with the matcher's database for replay, and
the page logged in to the dashboard as a viewer of its users file. The page must
show the tracks and the counts appearing and changing, the cameras online with a message
rate, and after the run replay the stored run at 10x to the same counts the matcher stored.
Screenshots are saved (to ``$CBLRS_SCREENSHOTS`` too when set, for README.md and docs/live.md).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
from dashboard_helpers import VIEWER, cblrs_command, login, wait_until

from cblrs.datasets import load_scene
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import count_summary, read_counts
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.protocol import Will
from cblrs.site import load_site

pytestmark = [pytest.mark.mqtt, pytest.mark.slow]

FRAMES = (0, 595)
PACE_S = 0.1  # 2 fps recorded, so ~5x real time


def save_screenshot(page, path: Path) -> None:
    page.screenshot(path=str(path))
    folder = os.environ.get("CBLRS_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, Path(folder) / path.name)


def stats(page) -> dict:
    return page.evaluate("JSON.parse(JSON.stringify(window.cblrsStats))")


def counts(page) -> dict:
    return page.evaluate("window.cblrsCounts()")


def line_total(page_counts: dict) -> int:
    return sum(row["positive"] + row["negative"] for row in page_counts["lines"].values())


def paced(frames, seconds):
    for frame in frames:
        yield frame
        time.sleep(seconds)


def test_live_dashboard_then_replay(wildtrack_root, wildtrack_site, start_broker,
                                    start_dashboard, users_file, page, tmp_path):
    site = load_site(wildtrack_site)
    scene = load_scene(wildtrack_root).select_frames(*FRAMES)
    names = scene.camera_names
    references = [site.render_reference(name) for name in names]
    broker = start_broker(cameras=names, matchers=["matcher1"])
    database = tmp_path / "matcher.db"
    matcher = subprocess.Popen(
        cblrs_command("matcher", "--site", str(wildtrack_site), "--db", str(database),
                      "--broker", broker.address, "--username", "matcher1",
                      "--password-file", str(broker.password_file("matcher1")),
                      "--window", "5", "--until-cameras-offline", "--idle-exit", "60"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_until(database.exists, 30, "the matcher's database")
        url = start_dashboard("--site", str(wildtrack_site), "--broker", broker.address,
                              "--username", "viewer", "--password-file",
                              str(broker.password_file("viewer")), "--db", str(database),
                              "--users", str(users_file)).url
        login(page, url, VIEWER)
        wait_until(lambda: stats(page)["connected"], 20, "the page's live stream")

        epoch = float(int(time.time()) - 300)
        threads = []
        for index, name in enumerate(names):

            def run(index=index, name=name) -> None:
                transport = MqttTransport(f"dash-{name}", broker.settings(name),
                                          persistent=False, will=Will(*camera_last_will(1, name)))
                transport.connect()
                # clear_retained as `cblrs camera` does: its empty publish is no message (the
                # page showed it as one rejected message per camera).
                node = CameraNode(transport, 1, name, references[index], epoch=epoch,
                                  clear_retained=True)
                node.run(paced(scene_source(scene, index), PACE_S), connect=False)
                transport.close()

            threads.append(threading.Thread(target=run, daemon=True))
        for thread in threads:
            thread.start()

        # Tracks appear, counts appear and change while the run goes on.
        wait_until(lambda: stats(page)["tracksShown"] >= 5, 60, "tracks on the map")
        wait_until(lambda: line_total(counts(page)) > 0, 60, "a counted crossing")
        first_total = line_total(counts(page))
        first_t = stats(page)["lastT"]
        wait_until(lambda: line_total(counts(page)) > first_total, 60, "the counts to change")
        wait_until(lambda: stats(page)["lastT"] > first_t, 30, "the tracks' time to move on")
        wait_until(lambda: stats(page)["live"] > 0, 30, "a live summary")
        # The camera health of the matcher's summaries: messages arriving from every camera
        # (a summary is published every second; under a loaded suite the first ones may
        # predate the cameras' first messages).
        wait_until(lambda: all(counts(page)["cameras"].get(name, {}).get("received", 0) > 0
                               for name in names), 30,
                   f"every camera's messages in the live summary: {counts(page)['cameras']}")
        cameras = counts(page)["cameras"]
        assert all(cameras[name]["online"] for name in names), cameras
        # The first frame is captured at the epoch itself (the scene's time 0): a camera whose
        # first message is all the summary has seen so far shows exactly the epoch.
        assert all(cameras[name]["last_capture"] >= epoch for name in names), cameras
        assert any(cameras[name]["rate_hz"] > 0 for name in names) or not any(
            thread.is_alive() for thread in threads), cameras
        assert all(cameras[name]["rejected"] == 0 for name in names), cameras
        rows = page.locator("#cameras tbody tr").count()
        assert rows == len(names)
        assert page.locator("#cameras td.rejected").all_inner_texts() == ["0"] * len(names)
        assert (page.inner_text("#line-rule")
                == "counted when: past 0.5 m each side, through the segment")
        # Well into the run (for the picture): tens of crossings counted.
        wait_until(lambda: line_total(counts(page)) >= 25 or not any(t.is_alive()
                                                                     for t in threads),
                   60, "more crossings")
        save_screenshot(page, tmp_path / "dashboard_live.png")
        live_stats = stats(page)

        for thread in threads:
            thread.join(60)
        _, err = matcher.communicate(timeout=120)
        assert matcher.returncode == 0, err
        # Stale marks go: once the stream ended, empty updates remove every track.
        wait_until(lambda: stats(page)["tracksShown"] == 0, 30, "stale marks to go")
    finally:
        if matcher.poll() is None:
            matcher.kill()
            matcher.wait()

    with RuntimeStore(database, read_only=True) as store:
        stored = count_summary(read_counts(store))
    live_counts = counts(page)
    for line, row in stored["lines"].items():
        for direction in ("positive", "negative"):
            assert live_counts["lines"][line][direction] == row.get(direction, 0)

    # Replay of the stored run at 10x ends with the same counts.
    page.select_option("#speed", "10")
    page.click("#replay-button")
    wait_until(lambda: stats(page)["mode"] == "replay" and stats(page)["tracksShown"] > 0, 30,
               "replayed tracks")
    save_screenshot(page, tmp_path / "dashboard_replay.png")
    wait_until(lambda: stats(page)["ended"], 60, "the end of the replay")
    replayed = counts(page)
    for line, row in stored["lines"].items():
        for direction in ("positive", "negative"):
            assert replayed["lines"][line][direction] == row.get(direction, 0), (line, replayed)
    for zone, row in stored["zones"].items():
        assert replayed["zones"][zone]["entries"] == row.get("entries", 0)
        assert replayed["zones"][zone]["visits"] == row.get("visits", 0)
    draws = live_stats["drawMs"]
    print(f"\nlive: {live_stats['tracksMessages']} track updates, {live_stats['draws']} draws, "
          f"median draw {sorted(draws)[len(draws) // 2]:.2f} ms; stored lines {stored['lines']}")
