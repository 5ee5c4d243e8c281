"""``cblrs up`` on the NATS backbone, with real processes: chosen by itself where Mosquitto is
not installed, secured (no anonymous client), tracks on the live map, SIGTERM stops it all;
a replay stopped half-way and restarted stores every message once."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
from up_helpers import (
    CAMERAS,
    ENVIRONMENT,
    PER_CAMERA,
    first_tracks_on_the_map,
    run_up,
    up_command,
)

from cblrs.runtime.broker.nats_server import find_nats_server
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport
from cblrs.runtime.transport.protocol import TransportError
from cblrs.up import database_counts

EXPECTED = {(name, sequence) for name in CAMERAS for sequence in range(PER_CAMERA)}


@pytest.fixture
def require_nats_server() -> None:
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]')")


def without_mosquitto(tmp_path) -> dict[str, str]:
    """The environment with a PATH holding no mosquitto (nor /usr/bin, so neither sbin)."""
    empty = tmp_path / "bin"
    empty.mkdir(exist_ok=True)
    return {**ENVIRONMENT, "PATH": str(empty)}


def test_without_mosquitto_it_runs_on_nats_tracks_reach_the_map_and_sigterm_stops_it(
        small_site, tmp_path, require_nats_server):
    out = tmp_path / "state"
    started = time.monotonic()
    process = subprocess.Popen(up_command(small_site, out, "--quiet"), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True,
                               env=without_mosquitto(tmp_path))
    try:
        line = process.stderr.readline()
        while line and not line.startswith("dashboard: "):
            line = process.stderr.readline()
        assert line, process.communicate()[1]
        rows = first_tracks_on_the_map(line.split(" ", 1)[1].strip(), timeout=90)
        on_the_map_s = time.monotonic() - started
        state = json.loads((out / "up.json").read_text())
        assert state["backbone"] == "nats"
        # secured like Mosquitto: a client without a login is refused
        anonymous = NatsTransport("anonymous", NatsSettings.from_url(
            f"nats://127.0.0.1:{state['broker_port']}", connect_timeout_s=5))
        with pytest.raises(TransportError):
            anonymous.connect()
        anonymous.close()
        process.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        stdout, stderr = process.communicate(timeout=90)
        stopped_in = time.monotonic() - sent
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert all(len(row) == 4 and isinstance(row[0], int) for row in rows), rows
    assert process.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["backbone"] == "nats" and summary["stopped_by"] == "signal"
    assert summary["broker"].startswith("nats://127.0.0.1:")
    assert set(summary["processes"]) == {"broker", "matcher-1", "dashboard", "camera-CVLab1",
                                         "camera-CVLab2"}
    assert {info["state"] for info in summary["processes"].values()} <= {"stopped",
                                                                         "finished"}, summary
    codes = {name: info["exit_code"] for name, info in summary["processes"].items()}
    assert {name: codes[name] for name in ("broker", "matcher-1", "dashboard")} == dict.fromkeys(
        ("broker", "matcher-1", "dashboard"), 0), codes  # a clean stop is 0, as on Mosquitto
    config = (out / "broker" / "n1" / "n1.conf").read_text()
    assert "authorization {" in config and "no_auth_user" not in config
    assert (out / "broker" / "n1" / "n1.conf").stat().st_mode & 0o077 == 0
    assert stopped_in < 20, stopped_in
    print(f"NATS: tracks on the map {on_the_map_s:.1f} s after cblrs up started; stopped in "
          f"{stopped_in:.1f} s")


def stored_keys(database) -> list[tuple[str, int]]:
    with RuntimeStore(database, read_only=True) as store:
        return sorted((item.message.camera_id, item.message.sequence)
                      for item in store.messages())


def test_on_nats_sigterm_mid_run_and_a_restart_store_every_message_once(
        small_site, tmp_path, require_nats_server):
    out = tmp_path / "state"
    process = subprocess.Popen(up_command(small_site, out, "--backbone", "nats",
                                          "--no-dashboard", "--until-done", "--speed", "2"),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=ENVIRONMENT)
    try:
        deadline = time.monotonic() + 120
        while sum(database_counts(out / "plane1.db")["stored"].values()) < 8:
            assert process.poll() is None, process.communicate()[1]
            assert time.monotonic() < deadline, "no message stored within 120 s"
            time.sleep(0.1)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=90)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["backbone"] == "nats" and summary["stopped_by"] == "signal"
    assert {info["state"] for info in summary["processes"].values()} == {"stopped"}, summary
    first = stored_keys(out / "plane1.db")
    assert 8 <= len(first) < len(EXPECTED)
    # the restart keeps the folder's backbone (auto) and its stream: nothing is missing, and
    # nothing is stored twice
    code, again, err = run_up(small_site, out, "--no-dashboard", "--until-done", timeout=240)
    assert code == 0, err
    assert again["backbone"] == "nats" and again["stopped_by"] == "done", again
    assert stored_keys(out / "plane1.db") == sorted(EXPECTED)
    plane = again["planes"]["1"]
    assert plane["pending"] == 0
    assert len((out / "tracks-plane1.txt").read_text().splitlines()) == plane["track_rows"] > 0
    # the state folder keeps its backbone: another one is one sentence
    code, summary, err = run_up(small_site, out, "--backbone", "mqtt", timeout=60)
    assert code == 1 and summary is None
    assert err.strip().count("\n") == 0 and "Traceback" not in err, err
    assert "holds a run on the nats backbone" in err or "mosquitto is not installed" in err
