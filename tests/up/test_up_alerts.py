"""``cblrs up`` on a site with alerts, as an operator runs it (real processes): the alerts
reach a webhook once each and ``cblrs up`` says what fired and what a webhook did not get;
a finished run starts again on its folder right after its stop (its broker's port still in
TIME_WAIT) and tracks what its cameras replay again; a webhook secret that cannot be read
stops it before anything starts."""

from __future__ import annotations

import json
import socket
import subprocess
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from up_helpers import CAMERAS, ENVIRONMENT, PER_CAMERA, run_up, up_command

from cblrs.alerts.webhook import verify

SECRET = b"op7-secret"


def alert_site(site: Path, url: str, extra: str = "") -> Path:
    """The small site with a zone, two rules that fire on its replay and a webhook."""
    secret = site.parent / "ops.secret"
    secret.write_bytes(SECRET)
    secret.chmod(0o600)
    text = site.read_text() + "\n".join([
        "  zones:",
        "    - {name: crossing, polygon: [[1.0, 11.5], [6.5, 11.5], [6.5, 15.5], [1.0, 15.5]]}",
        "alerts:",
        "  rules:",
        "    - {name: busy, kind: occupancy, zone: crossing, above: 0}",
        "    - {name: rush, kind: line_count, line: middle, above: 0, per_s: 600}",
        "  webhooks:",
        f"    - {{name: ops, url: '{url}', secret_file: ops.secret{extra}}}", ""])
    site.write_text(text)
    return site


class Receiver:
    """A webhook receiver on loopback: every genuine alert it got, as (episode, state)."""

    def __init__(self, port: int = 0):
        received = self.received = []

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                genuine = verify(SECRET, self.headers["X-Cblrs-Timestamp"], body,
                                 self.headers["X-Cblrs-Signature"])
                if genuine:
                    alert = json.loads(body)
                    received.append((alert["episode"], alert["state"]))
                self.send_response(200 if genuine else 401)
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def port_in_time_wait() -> int:
    """A loopback port whose server (binding as Mosquitto does, ``SO_REUSEADDR``) closed a
    connection first: the port stays in TIME_WAIT for a minute, as a stopped broker's does."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        accepted, _ = listener.accept()
        accepted.close()  # the server's side closes first
        client.recv(1)
        client.close()
    with socket.socket() as plain:  # a bind without SO_REUSEADDR fails: the case is real
        with pytest.raises(OSError):
            plain.bind(("127.0.0.1", port))
    return port


def test_alerts_reach_the_webhook_once_and_a_finished_run_restarts_at_once(
        small_site, tmp_path, require_mosquitto):
    receiver = Receiver()
    try:
        site = alert_site(small_site, receiver.url)
        out = tmp_path / "state"
        port = port_in_time_wait()
        code, summary, err = run_up(site, out, "--speed", "4", "--until-done",
                                    "--broker-port", str(port))
        assert code == 0, err
        assert summary["broker"] == f"127.0.0.1:{port}"
        alerts = summary["planes"]["1"]["alerts"]
        assert alerts["fired"] >= 1, (alerts, err)
        assert alerts["undelivered"] == {"broker": 0, "ops": 0}, alerts
        first = list(receiver.received)
        assert len(first) == len(set(first)) == alerts["fired"] + alerts["cleared"], first
        assert {episode for episode, _ in first} >= {"rush/middle/1"}, first

        # At once on the same folder, its port still in TIME_WAIT: the cameras replay again,
        # their earlier ends (retained "offline") do not end this run before they start.
        code, again, err = run_up(site, out, "--until-done", "--broker-port", str(port))
        assert code == 0, err
        assert again["stopped_by"] == "done" and again["failure"] is None
        plane = again["planes"]["1"]
        assert plane["counters"]["duplicates"] == len(CAMERAS) * PER_CAMERA, plane["counters"]
        assert plane["pending"] == 0
        assert {info["state"] for name, info in again["processes"].items()
                if name.startswith("camera-")} == {"finished"}, again["processes"]
        # nothing fired twice; what was firing at the first stop cleared once
        assert len(receiver.received) == len(set(receiver.received)), receiver.received
        fired = {episode for episode, state in receiver.received if state == "fired"}
        cleared = {episode for episode, state in receiver.received if state == "cleared"}
        assert set(plane["alerts"]["firing"]) == fired - cleared, (plane["alerts"],
                                                                   receiver.received)
    finally:
        receiver.close()


def test_alerts_a_webhook_did_not_get_are_said_and_sent_at_the_next_start(
        small_site, tmp_path, require_mosquitto):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    site = alert_site(small_site, f"http://127.0.0.1:{port}/hook", ", retries: 0")
    out = tmp_path / "state"
    command = [part for part in up_command(site, out, "--speed", "4", "--until-done")
               if part != "--json"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120,
                            env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines()
             if "not delivered to webhook ops" in line]
    assert len(lines) == 1, result.stdout
    assert lines[0].startswith("plane 1: ") and "the matcher sends them at the next cblrs up " \
        "on this --out (last failure: " in lines[0] and "Connection refused" in lines[0], lines
    count = int(lines[0].split()[2])
    assert count >= 1
    assert "plane 1: alerts " in result.stdout
    receiver = Receiver(port)
    try:
        code, summary, err = run_up(site, out, "--until-done")
        assert code == 0, err
        assert summary["planes"]["1"]["alerts"]["undelivered"]["ops"] == 0, summary["planes"]
        assert len(receiver.received) >= count, receiver.received
        assert len(receiver.received) == len(set(receiver.received)), receiver.received
    finally:
        receiver.close()


@pytest.mark.parametrize(("extra", "message"), [
    ("missing", "alerts: webhook ops: cannot read its secret file {folder}/ops.secret: No "
     "such file or directory."),
    ("open", "alerts: webhook ops: its secret file {folder}/ops.secret is readable by others "
     "(mode 0644); chmod 600 it."),
    ("env", "alerts: webhook ops: the environment variable CBLRS_OP7_UNSET (its secret) is "
     "not set."),
])
def test_a_webhook_secret_that_cannot_be_read_stops_it_before_anything_starts(
        small_site, tmp_path, extra, message):
    site = alert_site(small_site, "http://127.0.0.1:9/hook")
    secret = tmp_path / "ops.secret"
    if extra == "missing":
        secret.unlink()
    elif extra == "open":
        secret.chmod(0o644)
    else:
        site.write_text(site.read_text().replace("secret_file: ops.secret",
                                                 "secret_env: CBLRS_OP7_UNSET"))
    environment = {key: value for key, value in ENVIRONMENT.items()
                   if key != "CBLRS_OP7_UNSET"}
    code, summary, err = run_up(site, tmp_path / "state", timeout=60, environment=environment)
    assert code == 1 and summary is None, err
    assert err.strip().count("\n") == 0 and "Traceback" not in err, err
    assert err.strip() == f"cblrs up: error: {site.name}: " + message.format(folder=tmp_path)
    assert not (tmp_path / "state").exists()  # no broker configuration, no references
