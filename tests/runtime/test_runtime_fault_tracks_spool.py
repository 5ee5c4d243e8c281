"""A camera's spool never mixes two runs (issue 20, item 6): another run under the same
camera name is refused in one sentence, and given a spool of its own its messages reach the
matcher as conflicts, never tracked in the first run's place (Mosquitto, real processes;
the plant is in fault_tracks.py).
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import pytest
from fault_tracks import (
    CAMERAS,
    ENVIRONMENT,
    PER_CAMERA,
    assert_undisturbed,
    camera,
    finish,
    make_case,
    matcher,
    start,
)


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    return make_case(wildtrack_root, tmp_path_factory)


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
