"""Failover of the NATS JetStream backbone, the whole cluster: killed and restarted mid-stream
on the same stores (nothing lost, nothing tracked twice), and a matcher started before the
cluster has a JetStream leader waits for it. The plant and the checks are in
nats_failover_plant.py; see test_runtime_nats_failover.py.
"""

from __future__ import annotations

import time

import pytest
from nats_failover_plant import (
    NatsCluster,
    NatsSettings,
    NatsTransport,
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
    try_connect,
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


def test_whole_cluster_restarted_mid_stream(case, cluster, tmp_path, record_property):
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
            at_kill = counter(database, "accepted")
            killed = time.monotonic()
            nats.kill()
            time.sleep(0.5)
            nats.start()
            restarted = time.monotonic()
            wait_until(
                lambda: counter(database, "accepted") > at_kill, 60, "messages after the restart"
            )
            recovered = time.monotonic() - killed
            report = {
                "fault": "whole cluster killed and restarted",
                "accepted_at_kill": at_kill,
                "down_s": round(restarted - killed, 2),
                "recover_s": round(recovered, 2),
            }
            assert at_kill < total, "the restart was not mid-stream"
            finish(processes, cameras, probe, database, case, epoch, report, record_property)
    finally:
        cleanup(processes)


def test_a_matcher_started_before_the_cluster_has_a_jetstream_leader_waits(case, tmp_path):
    """Started with its cluster (one node of three up: no JetStream meta leader), the
    matcher waits for JetStream instead of exiting ("cannot open the NATS lease bucket:
    nats: timeout"), and serves the plane once the other nodes are up."""
    nats = NatsCluster.create(tmp_path / "nats", nodes=3)
    database = tmp_path / "matcher.db"
    probe = NatsTransport("test-probe", NatsSettings.from_url(nats.url))
    processes = []
    try:
        nats.nodes[0].launch().wait_ready()
        processes.append(start_matcher(case, nats, database, "host-a"))
        with matcher_logs_on_failure(database):
            wait_until(
                lambda: (
                    "JetStream does not answer yet" in log_tail(database)
                    or processes[0].poll() is not None
                ),
                60,
                "the matcher to wait",
            )
            assert processes[0].poll() is None, "the matcher exited"
            for node in nats.nodes[1:]:
                node.launch()
            wait_until(lambda: try_connect(probe), 30, "the cluster to accept clients")
            wait_for_consumer(probe, processes[0], database)
            assert "holds plane-1" in log_tail(database, 100_000)
    finally:
        cleanup(processes)
        probe.close(timeout=1)
        nats.kill()
