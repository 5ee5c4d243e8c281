"""The analytics on the wire: ``cblrs.events/1``, ``cblrs.live/1``, and the tracks message's
optional class and time."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.detections import Tracks
from cblrs.runtime.outputs.events import decode_event, decode_live, encode_event, encode_live
from cblrs.runtime.transport.nats_subjects import message_id
from cblrs.runtime.wire import RejectedMessage, RejectReason, decode_tracks, encode_tracks

LINE = {"kind": "line_crossed", "timestamp": 12.5, "track": 7, "place": "gate",
        "class": "person", "direction": "positive", "world_xy": [1.0, 2.0], "total": 3,
        "key": "line_crossed/gate/7/12.5"}
ENTERED = {"kind": "zone_entered", "timestamp": 3.0, "track": 2, "place": "hall",
           "crossed": True, "total": 1, "key": "zone_entered/hall/2/3.0"}
LEFT = {"kind": "zone_left", "timestamp": 9.0, "track": 2, "place": "hall",
        "entered_at": 3.0, "dwell_s": 6.0, "entered": True, "exited": False, "total": 1,
        "key": "zone_left/hall/2/9.0"}


@pytest.mark.parametrize("body", [LINE, ENTERED, LEFT])
def test_events_round_trip(body):
    payload = encode_event(body, plane_id=3, event_id=41)
    event = decode_event(payload)
    assert (event.plane, event.id, event.kind, event.key) == (3, 41, body["kind"], body["key"])
    document = json.loads(payload)
    assert document["schema"] == "cblrs.events/1"
    assert {key: document[key] for key in body} == body


@pytest.mark.parametrize(
    "change, reason, text",
    [
        ({"direction": None}, RejectReason.MISSING_FIELD, "needs direction"),
        ({"crossed": True}, RejectReason.UNKNOWN_FIELD, "has no crossed"),
        ({"kind": "line_jumped"}, RejectReason.INVALID_VALUE, "kind"),
        ({"direction": "up"}, RejectReason.INVALID_VALUE, "direction"),
        ({"total": -1}, RejectReason.INVALID_VALUE, "total"),
        ({"place": ""}, RejectReason.INVALID_VALUE, "place"),
        ({"class": "dragon" * 10}, RejectReason.INVALID_VALUE, "class"),
    ],
)
def test_bad_events_are_refused(change, reason, text):
    document = {"schema": "cblrs.events/1", "plane": 1, "id": 1, **LINE, **change}
    document = {key: value for key, value in document.items() if value is not None}
    with pytest.raises(RejectedMessage) as caught:
        decode_event(json.dumps(document).encode())
    assert caught.value.reason == reason and text in str(caught.value)


def test_event_payloads_refused_outright():
    with pytest.raises(RejectedMessage) as caught:
        decode_event(b'{"schema": "cblrs.tracks/1"}')
    assert caught.value.reason == RejectReason.WRONG_SCHEMA
    with pytest.raises(RejectedMessage) as caught:
        decode_event(b"x" * 5000)
    assert caught.value.reason == RejectReason.OVERSIZED
    with pytest.raises(RejectedMessage):
        decode_event(b'{"schema": "cblrs.events/1", "timestamp": NaN}')
    with pytest.raises(RejectedMessage):
        encode_event({**LINE, "timestamp": float("inf")}, 1, 1)


def test_live_summary_round_trip():
    summary = {
        "plane": 1, "sent_at": 100.0, "clock": 99.5,
        "cameras": [{"camera": "CVLab1", "online": True, "received": 10, "rejected": 1,
                     "rate_hz": 2.0, "last_capture": 99.0, "last_age_s": 0.3}],
        "lines": [{"line": "gate", "positive": 3, "negative": 1}],
        "zones": [{"zone": "hall", "occupancy": 2, "entries": 5, "exits": 3, "visits": 4,
                   "mean_dwell_s": 6.5, "dwell": [[7, 12.0], [9, 1.5]]}],
    }
    live = decode_live(encode_live(summary))
    assert live.cameras[0].rejected == 1 and live.zones[0].dwell[0] == (7, 12.0)
    with pytest.raises(RejectedMessage):
        encode_live({**summary, "cameras": [{"camera": "bad/id", "online": True}]})


def test_tracks_carry_class_and_time():
    tracks = Tracks(np.array([5, 5]), np.array([2.0, 2.0]), np.array([1, 2]),
                    np.array([[0.0, 1.0], [2.0, 3.0]]), class_id=np.array([0, -1]))
    payload = encode_tracks(tracks, 1, sequence=4, timestamp=2.0)
    document = json.loads(payload)
    assert document["tracks"][0]["class"] == "person" and "class" not in document["tracks"][1]
    update = decode_tracks(payload)
    assert update.timestamp == 2.0 and update.tracks.class_id.tolist() == [0, -1]
    # Old updates (no class, no time) still decode.
    del document["timestamp"]
    del document["tracks"][0]["class"]
    old = decode_tracks(json.dumps(document).encode())
    assert old.timestamp is None and old.tracks.class_id.tolist() == [-1, -1]
    document["tracks"][0]["class"] = "unicorn"
    with pytest.raises(RejectedMessage, match="unknown track class"):
        decode_tracks(json.dumps(document).encode())


def test_events_have_a_nats_message_id_from_their_key():
    payload = encode_event(LINE, 2, 9)
    assert message_id("cblrs.2.events", payload) == "events.2.line_crossed/gate/7/12.5"
