"""The matcher service with a site file tracks exactly as well as ``cblrs track``.

Everything runs as a user would run it: ``cblrs site init`` writes the site of WILDTRACK, a
real Mosquitto (started by the test on a free loopback port) carries the messages, the
matcher (``cblrs matcher --site``) and seven cameras (``cblrs camera --site``, one process
each, each rendering only its own reference) are separate processes, and the tracks the
matcher stored are scored against ``cblrs track`` on the same boxes. ``cblrs analytics`` reads
the matcher's ``--out-tracks`` as it is (its sidecar keeps the capture times; issue 21 found it
refused for want of a frame rate).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from waiting import wait_until

from cblrs.cli.main import main
from cblrs.datasets import load_scene, read_tracks
from cblrs.datasets.aicity import metadata_path
from cblrs.evaluation import evaluate
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import matcher_status_topic
from cblrs.runtime.wire import decode_status

REPO = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.mqtt, pytest.mark.slow]


def _command(*arguments: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", *arguments]


def test_service_with_site_scores_like_cblrs_track(wildtrack_root, mosquitto, tmp_path):
    site = tmp_path / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(site)]) == 0
    offline_tracks = tmp_path / "offline.txt"
    assert main(["track", str(wildtrack_root), "--out", str(offline_tracks), "--quiet"]) == 0
    truth = load_scene(wildtrack_root).ground_truth
    offline = evaluate(truth, read_tracks(offline_tracks))

    broker = f"127.0.0.1:{mosquitto.port}"
    online = threading.Event()
    watcher = MqttTransport("site-watcher", mosquitto.settings(), persistent=False)

    def on_status(delivery) -> None:
        if decode_status(delivery.payload).state == "online":
            online.set()
        delivery.ack()

    watcher.subscribe(matcher_status_topic(1, "site-matcher"), on_status)
    watcher.connect()
    service_tracks = tmp_path / "service.txt"
    # A long ordering window: cameras start seconds apart on a busy machine, and a group
    # must not be released before every camera has sent its frame.
    matcher = subprocess.Popen(
        _command(
            "matcher",
            "--site",
            str(site),
            "--db",
            str(tmp_path / "m.db"),
            "--client-id",
            "site-matcher",
            "--broker",
            broker,
            "--window",
            "120",
            "--until-cameras-offline",
            "--out-tracks",
            str(service_tracks),
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    cameras: list[subprocess.Popen] = []
    try:
        wait_until(
            lambda: online.is_set() or matcher.poll() is not None, 60, "the matcher to come online"
        )
        assert matcher.poll() is None, matcher.communicate()[1]
        epoch = str(int(time.time()) - 300)
        for name in ("CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3"):
            cameras.append(
                subprocess.Popen(
                    _command(
                        "camera",
                        "--dataset",
                        str(wildtrack_root),
                        "--camera",
                        name,
                        "--site",
                        str(site),
                        "--epoch",
                        epoch,
                        "--broker",
                        broker,
                        "--quiet",
                    ),
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                )
            )
        for camera in cameras:
            _, error = camera.communicate(timeout=180)
            assert camera.returncode == 0, error
        out, err = matcher.communicate(timeout=180)
    finally:
        for process in [matcher, *cameras]:
            if process.poll() is None:
                process.kill()
        watcher.close()
    assert matcher.returncode == 0, err
    # The start-up output says which cameras have positions.
    assert "camera positions for 7 of 7 cameras" in err, err
    assert "CVLab1 (9.10, -5.84, 2.89 m high) [calibration file]" in err
    assert "late 0" in out and "rejected 0" in out, out
    service = evaluate(truth, read_tracks(service_tracks))
    assert service.HOTA == pytest.approx(offline.HOTA, abs=0.01)
    assert offline.HOTA > 90.0

    # The matcher's tracks file goes straight into `cblrs analytics` (no --fps): its times are
    # the capture times, and its counts those of the same file with the frame rate given.
    sidecar = json.loads(metadata_path(service_tracks).read_text())
    assert sidecar["frames_per_second"] is None and "timestamps" in sidecar
    places = REPO / "sites" / "wildtrack.yaml"
    code = main(["analytics", str(service_tracks), "--site", str(places), "--out",
                 str(tmp_path / "timed"), "--no-plots", "--json"])
    assert code == 0
    timed = json.loads((tmp_path / "timed" / "analytics.json").read_text())
    code = main(["analytics", str(service_tracks), "--site", str(places), "--fps", "10", "--out",
                 str(tmp_path / "by-rate"), "--no-plots", "--json"])
    assert code == 0
    by_rate = json.loads((tmp_path / "by-rate" / "analytics.json").read_text())
    assert sum(row["count"] for row in timed["lines"]) > 10
    assert timed["lines"] == by_rate["lines"]
    for with_times, with_rate in zip(timed["zones"], by_rate["zones"], strict=True):
        for measure in ("entries", "appeared", "exits", "visits"):
            assert with_times[measure] == with_rate[measure]
    crossings = (tmp_path / "timed" / "crossings.csv").read_text().splitlines()
    assert float(crossings[1].split(",")[crossings[0].split(",").index("timestamp_s")]) > 1e9
