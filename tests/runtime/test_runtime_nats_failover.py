"""Failover of the NATS JetStream backbone on a 3-node cluster (loopback ports, own stores).

Each scenario replays 120 WILDTRACK frames of 7 cameras (paced, 10x real time) from camera
nodes publishing to JetStream (`cblrs camera --backbone nats://...` does the same), into a
`cblrs matcher --backbone nats://...` process, injects one fault mid-stream and then checks:

* messages lost = 0: every (camera, sequence) is in the final store, processed once;
* duplicated tracks = 0: the store's track rows equal an undisturbed in-process run on the
  same capture times, and the CBLRS_TRACKS stream holds one update per timestamp group;
* the time to recover, printed (run with ``-s``) and attached to the test report.

Faults: the stream leader is killed (SIGKILL); the matcher is killed and a new one starts on
another "host" (another --db and client id), taking over the plane's lease and rebuilding its
store from the stream (the whole cluster killed and restarted, and a matcher started before the
cluster has a JetStream leader, are in test_runtime_nats_failover_cluster.py; the plant is in
nats_failover_plant.py).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
from nats_failover_plant import (
    LEASE_TTL,
    cleanup,
    counter,
    finish,
    log_tail,
    make_case,
    matcher_logs_on_failure,
    needs_nats,
    running_cluster,
    start_cameras,
    start_matcher,
    stream_leader,
    wait_for_consumer,
)
from waiting import wait_until

pytestmark = [pytest.mark.nats, pytest.mark.slow]


@pytest.fixture(scope="module", autouse=True)
def _needs_nats():
    needs_nats()


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory):
    return make_case(wildtrack_root, tmp_path_factory)


@pytest.fixture
def cluster(tmp_path):
    yield from running_cluster(tmp_path)


def test_stream_leader_killed_mid_stream(case, cluster, tmp_path, record_property):
    nats, probe = cluster
    database = tmp_path / "matcher.db"
    processes = [start_matcher(case, nats, database, "host-a")]
    try:
        with matcher_logs_on_failure(database):
            wait_for_consumer(probe, processes[0], database)
            epoch = time.time() + 2.0
            cameras = start_cameras(case, nats, epoch)
            total = len(case["scene"].frames) * len(case["scene"].cameras)
            wait_until(lambda: counter(database, "accepted") >= total // 4, 60, "a quarter")
            leader = stream_leader(probe)
            assert leader is not None
            at_kill = counter(database, "accepted")
            killed = time.monotonic()
            nats.node(leader).kill()
            wait_until(
                lambda: counter(database, "accepted") > at_kill, 60, "messages after the kill"
            )
            recovered = time.monotonic() - killed
            wait_until(lambda: stream_leader(probe) not in (None, leader), 30, "a new leader")
            report = {
                "fault": "stream leader killed",
                "killed": leader,
                "new_leader": stream_leader(probe),
                "accepted_at_kill": at_kill,
                "recover_s": round(recovered, 2),
            }
            assert at_kill < total, "the kill was not mid-stream"
            finish(processes, cameras, probe, database, case, epoch, report, record_property)
    finally:
        cleanup(processes)


def test_matcher_killed_and_started_on_another_host(case, cluster, tmp_path, record_property):
    nats, probe = cluster
    first_database, second_database = tmp_path / "host-a.db", tmp_path / "host-b.db"
    processes = [start_matcher(case, nats, first_database, "host-a")]
    try:
        with matcher_logs_on_failure(first_database, second_database):
            wait_for_consumer(probe, processes[0], first_database)
            # A second matcher while the first holds the plane's lease is refused, in one sentence.
            # (Asked while host-a is alive: after a kill the lease lives only LEASE_TTL seconds,
            # less than a loaded machine may take to start a Python process.)
            refused = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "cblrs.cli.main",
                    "matcher",
                    "--references",
                    str(case["folder"]),
                    "--db",
                    str(tmp_path / "host-c.db"),
                    "--backbone",
                    nats.url,
                    "--client-id",
                    "host-c",
                    "--idle-exit",
                    "20",
                    "--quiet",
                ],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert refused.returncode == 1, refused.stderr
            assert "plane 1 is already served by host-a@" in refused.stderr
            assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
            epoch = time.time() + 2.0
            cameras = start_cameras(case, nats, epoch)
            total = len(case["scene"].frames) * len(case["scene"].cameras)
            wait_until(lambda: counter(first_database, "processed") >= total // 4, 60, "a quarter")
            processes[0].send_signal(signal.SIGKILL)
            processes[0].wait(10)
            killed = time.monotonic()
            processed_at_kill = counter(first_database, "processed")
            processes.append(
                start_matcher(case, nats, second_database, "host-b", "--lease-wait", "30")
            )
            wait_until(
                lambda: (
                    counter(second_database, "processed") >= processed_at_kill
                    or processes[1].poll() is not None
                ),
                120,
                "the new host to re-track what the old one had",
            )
            if processes[1].poll() is not None:  # say why, not only that it did not catch up
                raise AssertionError(
                    f"the new host exited with {processes[1].returncode}: "
                    f"{log_tail(second_database)}"
                )
            recovered = time.monotonic() - killed
            report = {
                "fault": "matcher killed, restarted on another host",
                "processed_at_kill": processed_at_kill,
                "recover_s": round(recovered, 2),
                "lease_ttl_s": LEASE_TTL,
            }
            assert processed_at_kill < total, "the kill was not mid-stream"
            finish(processes, cameras, probe, second_database, case, epoch, report, record_property)
    finally:
        cleanup(processes)
