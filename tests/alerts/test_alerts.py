"""Alerts: rules from a site file, episodes that fire once and clear once (also across a
restart, through their JSON state), and webhooks POSTed to a real local HTTP server — signed,
retried with back-off on 5xx and time-outs, never retried on a refusal."""

from __future__ import annotations

import json
import os
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
import yaml

from cblrs.alerts import AlertEpisodes, Observation, WebhookSender, load_alerts, read_secret
from cblrs.alerts.rules import AlertsError, WebhookModel
from cblrs.alerts.webhook import verify
from cblrs.cli.main import main
from cblrs.site import load_site
from cblrs.site.core import SiteError

SECRET = b"correct horse battery staple"


class Receiver:
    """A real HTTP server on a free loopback port that records requests and answers with the
    statuses it is told (then 200), optionally slowly."""

    def __init__(self, statuses=(), delay_s: float = 0.0):
        self.statuses = list(statuses)
        self.delay_s = delay_s
        self.requests: list[dict] = []
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                owner.requests.append({"at": time.monotonic(), "body": body,
                                       "headers": dict(self.headers)})
                if owner.delay_s and len(owner.requests) == 1:
                    time.sleep(owner.delay_s)
                status = owner.statuses.pop(0) if owner.statuses else 200
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver():
    made = []

    def make(*args, **kwargs) -> Receiver:
        made.append(Receiver(*args, **kwargs))
        return made[-1]

    yield make
    for item in made:
        item.close()


def hook(url: str, **options) -> WebhookModel:
    return WebhookModel(name="ops", url=url, secret_env="CBLRS_TEST_SECRET", **options)


# ---------------------------------------------------------------- webhooks


def test_an_alert_is_posted_signed(receiver):
    server = receiver()
    sender = WebhookSender(hook(server.url), SECRET)
    body = {"schema": "cblrs.alert/1", "episode": "crowd/market/1", "state": "fired"}
    result = sender.send(body)
    assert result.delivered and result.attempts == 1 and result.status == 200
    (request,) = server.requests
    headers = request["headers"]
    assert json.loads(request["body"]) == body
    assert headers["X-Cblrs-Episode"] == "crowd/market/1 fired"
    assert verify(SECRET, headers["X-Cblrs-Timestamp"], request["body"],
                  headers["X-Cblrs-Signature"])
    # Another secret, another body or an old timestamp do not verify.
    assert not verify(b"guess", headers["X-Cblrs-Timestamp"], request["body"],
                      headers["X-Cblrs-Signature"])
    assert not verify(SECRET, headers["X-Cblrs-Timestamp"], request["body"] + b" ",
                      headers["X-Cblrs-Signature"])
    assert not verify(SECRET, headers["X-Cblrs-Timestamp"], request["body"],
                      headers["X-Cblrs-Signature"], now=time.time() + 3600)


def test_failures_are_retried_with_back_off_and_refusals_are_not(receiver):
    server = receiver(statuses=[503, 500, 429])
    sender = WebhookSender(hook(server.url, backoff_s=0.2, retries=5), SECRET)
    result = sender.send({"episode": "e/1", "state": "fired"})
    assert result.delivered and result.attempts == 4
    gaps = [b["at"] - a["at"] for a, b in zip(server.requests, server.requests[1:],
                                                strict=False)]
    # 0.2, 0.4, 0.8 s of back-off (and never less).
    assert [round(gap, 1) >= expected for gap, expected in zip(gaps, (0.2, 0.4, 0.8),
                                                                strict=True)] == [True] * 3
    # Every attempt of one alert is signed afresh, and names the same episode.
    assert {r["headers"]["X-Cblrs-Episode"] for r in server.requests} == {"e/1 fired"}
    refused = receiver(statuses=[403])
    result = WebhookSender(hook(refused.url, backoff_s=0.05), SECRET).send({"episode": "e/2"})
    assert not result.delivered and result.attempts == 1 and result.status == 403
    assert "HTTP 403" in result.error


def test_a_slow_receiver_times_out_and_is_tried_again(receiver):
    server = receiver(delay_s=1.5)
    sender = WebhookSender(hook(server.url, timeout_s=0.3, backoff_s=0.1, retries=2), SECRET)
    started = time.monotonic()
    result = sender.send({"episode": "e/1", "state": "fired"})
    assert result.delivered and result.attempts == 2
    assert time.monotonic() - started < 15  # not the slow answer's time times the retries


def test_an_unreachable_receiver_gives_up_after_its_retries(receiver):
    server = receiver()
    url = server.url
    server.close()
    result = WebhookSender(hook(url, backoff_s=0.05, retries=2), SECRET).send({"episode": "x"})
    assert not result.delivered and result.attempts == 3 and result.status is None


def test_the_background_sender_keeps_the_order(receiver):
    server = receiver()
    sender = WebhookSender(hook(server.url), SECRET)
    for number in range(5):
        sender.submit({"episode": f"e/{number}", "state": "fired"})
    deadline = time.monotonic() + 30
    while len(sender.results) < 5 and time.monotonic() < deadline:
        time.sleep(0.02)
    sender.close()
    assert [json.loads(r["body"])["episode"] for r in server.requests] == [
        f"e/{number}" for number in range(5)]


def test_secrets_come_from_an_owner_only_file_or_the_environment(tmp_path):
    path = tmp_path / "ops.secret"
    path.write_bytes(SECRET + b"\n")
    path.chmod(0o644)
    webhook = WebhookModel(name="ops", url="https://ops.example/x", secret_file="ops.secret")
    with pytest.raises(AlertsError, match=r"readable by others \(mode 0644\); chmod 600 it"):
        read_secret(webhook, tmp_path)
    path.chmod(0o600)
    assert read_secret(webhook, tmp_path) == SECRET
    by_env = hook("https://ops.example/x")
    assert read_secret(by_env, environment={"CBLRS_TEST_SECRET": "s3"}) == b"s3"
    with pytest.raises(AlertsError, match=r"CBLRS_TEST_SECRET .* is not set"):
        read_secret(by_env, environment={})


# ---------------------------------------------------------------- the site file

SITE = {
    "version": 1,
    "places": {"zones": [{"name": "market", "polygon": [[0, 0], [10, 0], [10, 10], [0, 10]]}],
               "lines": [{"name": "gate", "start": [0, -5], "end": [0, 5]}]},
    "alerts": {
        "rules": [
            {"name": "crowd", "kind": "occupancy", "zone": "market", "above": 2, "for_s": 10},
            {"name": "loitering", "kind": "dwell", "zone": "market", "above_s": 60},
            {"name": "rush", "kind": "line_count", "line": "gate", "above": 3, "per_s": 60},
            {"name": "down", "kind": "camera_offline", "for_s": 20},
            {"name": "behind", "kind": "matcher_lag", "above_s": 10, "for_s": 5},
        ],
        "webhooks": [{"name": "ops", "url": "https://ops.example/cblrs",
                      "secret_env": "CBLRS_OPS_SECRET"}],
    },
}


def write_site(tmp_path, document) -> str:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return str(path)


def test_the_site_file_holds_the_rules(tmp_path):
    site = load_site(write_site(tmp_path, SITE))
    assert [rule.kind for rule in site.alerts.rules] == [
        "occupancy", "dwell", "line_count", "camera_offline", "matcher_lag"]
    assert site.alerts.webhooks[0].secret_env == "CBLRS_OPS_SECRET"
    # The section survives `cblrs site export`.
    assert main(["site", "export", write_site(tmp_path, SITE), "--out",
                 str(tmp_path / "bundle.yaml"), "--quiet"]) == 0
    assert load_site(tmp_path / "bundle.yaml").alerts == site.alerts


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: a["webhooks"][0].update(secret="hunter2"),
         r"alerts.webhooks\[0\] \(ops\): a webhook's secret never goes in the site file in "
         "clear"),
        (lambda a: a["webhooks"][0].update(url="ftp://x/y"),
         "url must be an http:// or https:// address"),
        (lambda a: a["webhooks"][0].update(url="https://me:pw@x/y"),
         "must not carry a user or password"),
        (lambda a: a["webhooks"][0].pop("secret_env"),
         "give exactly one of secret_file or secret_env"),
        (lambda a: a["rules"][0].update(zone="plaza"),
         r"alerts.rules\[0\] \(crowd\): the site has no zone 'plaza' \(market\)"),
        (lambda a: a["rules"][2].update(line="exit"), "the site has no line 'exit' \\(gate\\)"),
        (lambda a: a["rules"][0].update(above=-1), "greater than or equal to 0"),
        # A typo in a rule's kind, key or section: the path as the file writes it (no
        # pydantic union tag), the rule's name, and what is allowed.
        (lambda a: a["rules"][1].update(kind="loud"),
         r"^site.yaml: alerts.rules\[1\] \(loitering\): kind must be one of occupancy, dwell, "
         r"line_count, camera_offline, matcher_lag; got 'loud'\.$"),
        (lambda a: a["rules"][0].update(for_s=-2),
         r"^site.yaml: alerts.rules\[0\] \(crowd\).for_s: Input should be greater than or "
         r"equal to 0\.$"),
        (lambda a: a["rules"][0].update(fors=3),
         r"^site.yaml: alerts.rules\[0\] \(crowd\).fors: unknown key \(allowed: name, kind, "
         r"zone, above, for_s\)\.$"),
        (lambda a: a["rules"][0].pop("kind"), r"alerts.rules\[0\] \(crowd\): a rule needs kind"),
        (lambda a: a["rules"][0].pop("above"),
         r"alerts.rules\[0\] \(crowd\).above: required key is missing\.$"),
        (lambda a: a["webhooks"][0].update(retry=3),
         r"alerts.webhooks\[0\] \(ops\).retry: unknown key \(allowed: name, url, "),
        (lambda a: a.update(rule=a.pop("rules")),
         r"^site.yaml: alerts.rule: unknown key \(allowed: rules, webhooks\)\.$"),
        (lambda a: a["rules"].append(dict(a["rules"][0])), "two rules are named 'crowd'"),
    ],
)
def test_bad_alert_sections_are_one_sentence(tmp_path, change, message):
    document = json.loads(json.dumps(SITE))
    change(document["alerts"])
    with pytest.raises(SiteError, match=message) as caught:
        load_site(write_site(tmp_path, document))
    assert str(caught.value).startswith("site.yaml: alerts")
    assert "hunter2" not in str(caught.value)


# ---------------------------------------------------------------- episodes


def rules(*items):
    return load_alerts({"rules": list(items)})


def states(events):
    return [(event.rule, event.subject, event.state) for event in events]


def test_occupancy_above_n_for_t_fires_once_and_clears_once():
    episodes = AlertEpisodes(rules(
        {"name": "crowd", "kind": "occupancy", "zone": "m", "above": 2, "for_s": 10}))
    seen = []
    # 3 people from t=5 to t=30 (a dip to 2 at t=12 restarts the wait), then 1.
    for t, count in [(0, 1), (5, 3), (10, 3), (12, 2), (13, 3), (20, 3), (23, 3), (30, 3),
                     (31, 1), (40, 1), (41, 3), (45, 3)]:
        for event in episodes.observe(Observation(t, occupancy={"m": count})):
            seen.append((t, event.state, event.episode, event.since, event.value))
    assert seen == [(23, "fired", "crowd/m/1", 13, 3.0), (31, "cleared", "crowd/m/1", 13, 1.0)]


def test_an_episode_survives_a_restart_without_firing_twice():
    model = rules({"name": "crowd", "kind": "occupancy", "zone": "m", "above": 2, "for_s": 5},
                  {"name": "rush", "kind": "line_count", "line": "g", "above": 2, "per_s": 10})
    first = AlertEpisodes(model)
    events = first.observe(Observation(0, occupancy={"m": 3},
                                       crossings=(("g", "positive", 0.0),) * 2))
    events += first.observe(Observation(6, occupancy={"m": 3},
                                        crossings=(("g", "negative", 5.0),)))
    assert states(events) == [("crowd", "m", "fired"), ("rush", "g", "fired")]
    state = json.loads(json.dumps(first.get_state()))
    restarted = AlertEpisodes(model)
    restarted.set_state(state)
    # Still above: nothing again; then the clears, once.
    assert restarted.observe(Observation(7, occupancy={"m": 4})) == []
    cleared = restarted.observe(Observation(16, occupancy={"m": 0}))
    assert states(cleared) == [("crowd", "m", "cleared"), ("rush", "g", "cleared")]
    assert [event.episode for event in cleared] == ["crowd/m/1", "rush/g/1"]
    # The next episode has the next number.
    restarted.observe(Observation(17, occupancy={"m": 3}))
    assert [e.episode for e in restarted.observe(Observation(23, occupancy={"m": 3}))] == [
        "crowd/m/2"]


def test_dwell_camera_offline_and_lag():
    episodes = AlertEpisodes(rules(
        {"name": "loiter", "kind": "dwell", "zone": "m", "above_s": 60},
        {"name": "down", "kind": "camera_offline", "for_s": 20},
        {"name": "behind", "kind": "matcher_lag", "above_s": 10, "for_s": 5},
    ))
    timeline = [
        Observation(0, longest_visit_s={"m": 30}, camera_silence_s={"a": 0.1, "b": 0.2},
                    lag_s=1),
        Observation(40, longest_visit_s={"m": 70}, camera_silence_s={"a": 0.1, "b": 15},
                    lag_s=12),
        Observation(46, longest_visit_s={"m": 76}, camera_silence_s={"a": 0.1, "b": 21},
                    lag_s=12),
        Observation(61, longest_visit_s={"m": 0}, camera_silence_s={"a": 0.1, "b": 36},
                    cameras_offline=frozenset({"b"}), lag_s=2),
        Observation(70, camera_silence_s={"a": 0.1, "b": 0.3}, lag_s=2),
    ]
    seen = [(observation.timestamp, *item) for observation in timeline
            for item in states(episodes.observe(observation))]
    assert seen == [
        (40, "loiter", "m", "fired"),
        (46, "behind", "matcher", "fired"),
        (61, "loiter", "m", "cleared"),
        (61, "down", "b", "fired"),
        (61, "behind", "matcher", "cleared"),
        (70, "down", "b", "cleared"),
    ]


def test_a_changed_rule_starts_afresh_and_old_observations_are_ignored():
    before = rules({"name": "crowd", "kind": "occupancy", "zone": "m", "above": 2})
    episodes = AlertEpisodes(before)
    assert states(episodes.observe(Observation(0, occupancy={"m": 3}))) == [
        ("crowd", "m", "fired")]
    assert episodes.observe(Observation(-5, occupancy={"m": 0})) == []  # older: ignored
    after = AlertEpisodes(rules({"name": "crowd", "kind": "occupancy", "zone": "m",
                                 "above": 5}))
    after.set_state(episodes.get_state())
    assert after.firing() == []


def test_the_receiver_sees_each_episode_fired_then_cleared(receiver, monkeypatch):
    # The pieces together: episodes -> the webhook -> a real HTTP server, which verifies.
    monkeypatch.setenv("CBLRS_TEST_SECRET", SECRET.decode())
    server = receiver(statuses=[502])
    webhook = hook(server.url, backoff_s=0.05)
    sender = WebhookSender(webhook, read_secret(webhook))
    episodes = AlertEpisodes(rules(
        {"name": "crowd", "kind": "occupancy", "zone": "m", "above": 1, "for_s": 2}))
    for t, count in [(0, 2), (3, 2), (4, 0)]:
        for event in episodes.observe(Observation(t, occupancy={"m": count})):
            assert sender.send(event.to_dict()).delivered
    delivered = {}
    for request in server.requests:
        headers = request["headers"]
        assert verify(os.environ["CBLRS_TEST_SECRET"].encode(), headers["X-Cblrs-Timestamp"],
                      request["body"], headers["X-Cblrs-Signature"])
        body = json.loads(request["body"])
        delivered.setdefault((body["episode"], body["state"]), body)
    assert list(delivered) == [("crowd/m/1", "fired"), ("crowd/m/1", "cleared")]
    assert len(server.requests) == 3  # the 502 was retried


# ---------------------------------------------------------------- in the matcher's SQLite


def test_the_ledger_survives_a_kill_and_delivers_each_alert_once(tmp_path, receiver):
    from cblrs.alerts import AlertLedger
    from cblrs.runtime.matcher.store import RuntimeStore

    model = rules({"name": "crowd", "kind": "occupancy", "zone": "m", "above": 1, "for_s": 2})
    database = tmp_path / "plane1.db"
    store = RuntimeStore(database)
    ledger = AlertLedger(store, model)
    assert ledger.observe(Observation(0, occupancy={"m": 2})) == []
    assert states(ledger.observe(Observation(3, occupancy={"m": 2}))) == [
        ("crowd", "m", "fired")]
    store.close()  # the matcher dies here: nothing else was saved

    store = RuntimeStore(database)
    ledger = AlertLedger(store, model)  # a restarted matcher on the same file
    assert ledger.observe(Observation(5, occupancy={"m": 3})) == []  # not fired again
    assert states(ledger.observe(Observation(9, occupancy={"m": 0}))) == [
        ("crowd", "m", "cleared")]
    assert [(a["episode"], a["state"]) for a in ledger.recent()] == [
        ("crowd/m/1", "cleared"), ("crowd/m/1", "fired")]

    # The outbox: a receiver that is down keeps both; once up, each is delivered once.
    down = receiver()
    url = down.url
    down.close()
    senders = {"ops": WebhookSender(hook(url, backoff_s=0.05, retries=1), SECRET)}
    assert ledger.deliver(senders) == 0
    up = receiver()
    senders = {"ops": WebhookSender(hook(up.url), SECRET)}
    assert ledger.deliver(senders) == 2
    assert ledger.deliver(senders) == 0
    assert [json.loads(r["body"])["state"] for r in up.requests] == ["fired", "cleared"]
    assert all(a["delivered_to"] == ["ops"] for a in ledger.recent())
    store.close()
