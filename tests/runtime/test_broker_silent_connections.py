"""Connections that never log in cannot keep a camera out of a Mosquitto that cblrs starts
(real Mosquitto with the generated configuration).

Mosquitto 2.0 keeps a TCP connection that never sends its MQTT ``CONNECT`` for about 90 s
and has no setting to shorten it, so anyone who reaches the port holds a file descriptor per
connection, without a login, until the broker's open-files limit is used up; then it accepts
nobody, a camera's login included. The limit is what a broker inherits: a shell's or
systemd's soft limit (1,024, a few hundred connections a second for 90 s). cblrs now starts
Mosquitto with its soft limit raised to the hard one (`MosquittoProcess`, `cblrs up`; the
broker's systemd unit sets ``LimitNOFILE=``). Here the starting process has a soft limit of
128 (scaled down from 1,024: the attack is 300 connections, not 1,100) and a hard one of
what the test has.
"""

from __future__ import annotations

import os
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from broker_user import RUN_AS

from cblrs.runtime.broker.mosquitto_config import find_mosquitto, free_port, write_broker_config
from cblrs.runtime.transport.mqtt_transport import MqttTransport

pytestmark = pytest.mark.mqtt

SOFT = 128
SILENT = 300
START = """
import sys
from cblrs.runtime.broker.mosquitto_config import MosquittoProcess
broker = MosquittoProcess(sys.argv[1], int(sys.argv[2])).start()
print(broker.pid, flush=True)
sys.stdin.read()
broker.stop()
"""


def open_files_soft_limit(pid: int) -> int:
    for line in Path(f"/proc/{pid}/limits").read_text().splitlines():
        if line.startswith("Max open files"):
            return int(line.split()[3])
    raise AssertionError(f"no open-files limit for {pid}")


def test_silent_connections_do_not_keep_a_camera_out(tmp_path):
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < SILENT + 200:
        pytest.skip(f"the hard open-files limit {hard} is below the attack")
    files = write_broker_config(tmp_path / "broker", ["CVLab1"], ["matcher1"], port=free_port(),
                                run_as=RUN_AS, plane_ids=(1,))
    # The broker's starter runs with a low soft limit (as under a shell or systemd).
    starter = subprocess.Popen(
        ["prlimit", f"--nofile={SOFT}:{hard if hard != resource.RLIM_INFINITY else 'unlimited'}",
         sys.executable, "-c", START, str(files.config), str(files.port)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    silent: list[socket.socket] = []
    try:
        line = starter.stdout.readline() if starter.stdout else ""
        assert line.strip().isdecimal(), f"the broker did not start: {line!r}"
        pid = int(line)
        for _ in range(SILENT):  # connect, never send CONNECT
            silent.append(socket.create_connection(("127.0.0.1", files.port), timeout=5))
        time.sleep(1.0)  # the broker accepts what it can
        camera = MqttTransport("CVLab1", files.settings("CVLab1", connect_timeout_s=5.0),
                               persistent=False)
        try:
            camera.connect()  # before: refused (the broker out of open files), 5 s time-out
            assert camera.connected
        finally:
            camera.close(timeout=1)
        assert open_files_soft_limit(pid) > SILENT
    finally:
        for connection in silent:
            connection.close()
        if starter.stdin:
            starter.stdin.close()
        starter.wait(30)
