"""Tracks after a matcher fault on NATS JetStream equal the undisturbed run's (issue 20):
item 2, a matcher killed while it held deliveries, restarted on the same --db; item 3,
re-sent messages the matcher had stored and never confirmed. The plant is in fault_tracks.py.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
from fault_tracks import (
    CAMERAS,
    ENVIRONMENT,
    TOTAL,
    assert_undisturbed,
    camera,
    counter,
    finish,
    make_case,
    matcher,
    nats_backbone,
    start,
    undisturbed_tracks,
)
from waiting import wait_until

from cblrs.runtime.transport.nats_subjects import detections_stream
from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    return make_case(wildtrack_root, tmp_path_factory)


@pytest.fixture
def nats(tmp_path):
    yield from nats_backbone(tmp_path)


# -- item 2 ----------------------------------------------------------------------------------


def freeze_holding_deliveries(matcher: subprocess.Popen, database, held) -> None:
    """Stop ``matcher`` (SIGSTOP) mid-stream so that it holds deliveries it never
    acknowledged (``held()``: the consumer's count of them).

    Frozen just after acknowledging everything, it holds some only if JetStream delivers
    more to its pull request, and that request may have expired (after 5 s) or just been
    answered: then it is resumed until it accepted more, and frozen again."""
    accepted = 9
    while True:
        wait_until(lambda floor=accepted: counter(database, "accepted") > floor, 60,
                   "more messages")
        matcher.send_signal(signal.SIGSTOP)  # acknowledges nothing more; deliveries pile up
        # A pull request expires within 5 s: longer than that, none is left to deliver to.
        deadline = time.monotonic() + 8
        while held() <= 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        if held() > 0:
            return
        accepted = counter(database, "accepted")
        assert accepted < TOTAL, "the cameras finished before the matcher held a delivery"
        matcher.send_signal(signal.SIGCONT)


@pytest.mark.nats
def test_item2_a_restarted_matcher_gets_its_pending_messages_at_once(case, nats, tmp_path):
    """The matcher dies holding deliveries it never acknowledged (frozen, then killed, so
    it certainly held some). Restarted on the same --db, it gets them at once — JetStream
    would hand them out again only after ack_wait (30 s), behind newer ones, and they would
    be late — and the tracks are the undisturbed run's. The cameras do not send anything
    again meanwhile (--resend-after 300)."""
    database = tmp_path / "plane1.db"
    lease = ["--lease-ttl", "3", "--lease-wait", "60"]
    first = start(matcher(case, database, nats, *lease))
    probe = NatsTransport("probe", NatsSettings.from_url(nats[1]))
    probe.connect()
    try:
        def held() -> int:
            try:
                return probe.call(probe.jetstream.consumer_info(
                    detections_stream(1), "cblrs-plane-1"), 5).num_ack_pending
            except Exception:  # no consumer yet
                return -1

        wait_until(lambda: held() >= 0, 60, "the matcher's consumer")
        # Paced: 20 s of scene in 20 s, from 10 s on (a camera process that starts late under
        # load sends its overdue frames at once, and the kill would come after them all).
        epoch = time.time() + 10.0
        cameras = [start(camera(case, tmp_path, name, nats, "--realtime",
                                "--confirm-timeout", "120", "--resend-after", "300",
                                epoch=epoch))
                   for name in CAMERAS]
        freeze_holding_deliveries(first, database, held)
        first.send_signal(signal.SIGKILL)
        first.communicate()
        assert counter(database, "accepted") < TOTAL, "the kill was not mid-stream"
        second = start(matcher(case, database, nats, *lease, "--until-cameras-offline",
                               "--idle-exit", "120"))
        for process in cameras:
            code, out, err = finish(process, timeout=240)
            assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
        code, out, err = finish(second, timeout=240)
        assert code == 0, err[-3000:]
        summary = json.loads(out)
        assert summary["late"] == 0 and summary["processed"] == TOTAL, summary
        assert_undisturbed(database, case, undisturbed_tracks(case, epoch))
    finally:
        probe.close(timeout=1)
        if first.poll() is None:
            first.kill()
            first.communicate()


# -- item 3 ----------------------------------------------------------------------------------


@pytest.mark.nats
def test_item3_resent_messages_reach_a_confirmation_on_nats(case, nats, tmp_path):
    """The matcher stored everything but its confirmations never reached the cameras (they
    had left before it started): the spools send it all again. On JetStream a re-send with
    the first publish's Nats-Msg-Id would be dropped as a duplicate and never confirmed
    (cameras exit 3, the matcher waits forever); re-sends carry their own id, the matcher
    sees them as duplicates and confirms them."""
    database = tmp_path / "plane1.db"
    unconfirmed = 0
    # Publish and leave before any matcher runs, so that no confirmation can reach a camera
    # (with the matcher already running, a camera slowed down by load was confirmed before it
    # left, and the test had nothing to re-send).
    for name in CAMERAS:
        result = subprocess.run(camera(case, tmp_path, name, nats, "--confirm-timeout", "0"),
                                capture_output=True, text=True, env=ENVIRONMENT, timeout=240)
        report = json.loads(result.stdout)
        assert result.returncode == 0 and report["flushed"], result.stderr
        unconfirmed += report["unconfirmed"]
    assert unconfirmed == TOTAL
    first = start(matcher(case, database, nats, "--until-cameras-offline", "--idle-exit", "60"))
    code, out, err = finish(first)
    assert code == 0, err[-3000:]
    assert json.loads(out)["processed"] == TOTAL
    second = start(matcher(case, database, nats, "--until-cameras-offline", "--idle-exit", "60"))
    resent = [start(camera(case, tmp_path, name, nats, "--confirm-timeout", "60",
                           replay=False)) for name in CAMERAS]
    for process in resent:
        code, out, err = finish(process)
        report = json.loads(out)
        if not (code == 0 and report["confirmed_all"]):  # the matcher's side of it too
            second.kill()
            pytest.fail(f"camera exit {code}: {err[-3000:]}\nmatcher: {finish(second)[2][-3000:]}")
        assert report["messages"] == 0
    code, out, err = finish(second)
    assert code == 0, err[-3000:]
    summary = json.loads(out)
    # Every re-sent message reached the matcher (and maybe some the consumer handed out
    # again: whatever lay above its acknowledgement floor when the first matcher stopped).
    assert summary["duplicates"] >= unconfirmed and summary["accepted"] == TOTAL, summary
    assert_undisturbed(database, case)
