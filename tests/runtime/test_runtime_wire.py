"""Wire format: round trips, every rejection reason, fuzzing; topic names."""

from __future__ import annotations

import json
import math

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.runtime.transport.topics import (
    TopicError,
    detections_filter,
    detections_topic,
    matcher_status_topic,
    parse_detections_topic,
    parse_status_topic,
    status_topic,
    tracks_topic,
    validate_camera_id,
)
from cblrs.runtime.wire import (
    DETECTIONS_SCHEMA,
    MAX_DETECTIONS,
    RejectedMessage,
    RejectReason,
    ValidationPolicy,
    decode_message,
    decode_message_with_plane,
    decode_status,
    decode_tracks,
    decode_wire,
    encode_message,
    encode_status,
    encode_tracks,
)

NOW = 1_700_000_000.0


def make_message(
    count: int = 2, camera_id: str = "CVLab1", timestamp: float = NOW
) -> CameraMessage:
    rng = np.random.default_rng(count)
    low = rng.uniform(0, 1000, size=(count, 2))
    size = rng.uniform(0, 200, size=(count, 2))
    return CameraMessage(
        camera_id=camera_id,
        sequence=7,
        timestamp=timestamp,
        frame=35,
        xyxy=np.hstack([low, low + size]),
        confidence=rng.uniform(0, 1, count),
        class_id=rng.integers(0, len(CLASS_NAMES), count),
        colour=rng.integers(0, 65536, size=(count, 3)),
    )


def assert_same_message(actual: CameraMessage, expected: CameraMessage) -> None:
    assert actual.camera_id == expected.camera_id
    assert actual.sequence == expected.sequence
    assert actual.timestamp == expected.timestamp
    assert actual.frame == expected.frame
    for name in ("xyxy", "confidence", "class_id", "colour"):
        assert np.array_equal(getattr(actual, name), getattr(expected, name)), name
        assert getattr(actual, name).dtype == getattr(expected, name).dtype, name
    assert actual.xyxy.shape == (len(expected), 4) and actual.colour.shape == (len(expected), 3)


def document(**changes) -> dict:
    """A valid message as a dict, with some fields replaced (None value: field removed)."""
    base = json.loads(encode_message(make_message(1), plane_id=1))
    for key, value in changes.items():
        if value is None:
            base.pop(key)
        else:
            base[key] = value
    return base


def detection(**changes) -> dict:
    item = {"class": "person", "confidence": 0.5, "box": [1.0, 2.0, 3.0, 4.0], "colour": [1, 2, 1]}
    for key, value in changes.items():
        if value is None:
            item.pop(key)
        else:
            item[key] = value
    return item


def raw(data) -> bytes:
    return json.dumps(data).encode()


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("count", [0, 1, 5, MAX_DETECTIONS])
def test_round_trip(count):
    message = make_message(count)
    payload = encode_message(message, plane_id=3)
    decoded, plane = decode_message_with_plane(payload, now=NOW)
    assert plane == 3
    assert_same_message(decoded, message)
    assert len(payload) <= 256 * 1024


def test_payload_is_readable_json_with_the_schema_first():
    payload = encode_message(make_message(1), plane_id=1)
    assert payload.startswith(b'{"schema":"cblrs.detections/1","camera":"CVLab1"')
    data = json.loads(payload)
    assert set(data) == {
        "schema",
        "camera",
        "sequence",
        "timestamp",
        "frame",
        "plane",
        "detections",
    }
    assert set(data["detections"][0]) == {"class", "confidence", "box", "colour"}
    assert data["detections"][0]["class"] in CLASS_NAMES


camera_ids = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}\Z")
finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e6, max_value=1e6)


@st.composite
def messages(draw):
    count = draw(st.integers(0, 12))
    corners = [sorted(draw(st.lists(finite, min_size=2, max_size=2))) for _ in range(2 * count)]
    xyxy = np.array(
        [
            [corners[2 * i][0], corners[2 * i + 1][0], corners[2 * i][1], corners[2 * i + 1][1]]
            for i in range(count)
        ],
        dtype=np.float64,
    ).reshape(-1, 4)
    return CameraMessage(
        camera_id=draw(camera_ids),
        sequence=draw(st.integers(0, 2**53)),
        timestamp=draw(st.floats(0, 4e9, allow_nan=False)),
        frame=draw(st.integers(0, 2**53)),
        xyxy=xyxy,
        confidence=np.array(draw(st.lists(st.floats(0, 1), min_size=count, max_size=count))),
        class_id=np.array(
            draw(st.lists(st.integers(0, len(CLASS_NAMES) - 1), min_size=count, max_size=count)),
            dtype=np.int64,
        ),
        colour=np.array(
            draw(st.lists(st.integers(0, 65535), min_size=3 * count, max_size=3 * count)),
            dtype=np.int64,
        ).reshape(-1, 3),
    )


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(message=messages(), plane=st.integers(1, 65535))
def test_valid_messages_round_trip_exactly(message, plane):
    decoded, decoded_plane = decode_message_with_plane(
        encode_message(message, plane), now=message.timestamp
    )
    assert decoded_plane == plane
    assert_same_message(decoded, message)


# --------------------------------------------------------------------------- rejections

OVERSIZE = 1024

REJECTIONS = [
    # (payload, keyword arguments, reason, text in the detail)
    (b"{", {}, RejectReason.MALFORMED_JSON, "truncated"),
    (b"", {}, RejectReason.MALFORMED_JSON, "truncated"),
    (b"\xff\xfe", {}, RejectReason.MALFORMED_JSON, "malformed"),
    (b"[1, 2]", {}, RejectReason.MALFORMED_JSON, "top level is list"),
    (b'"text"', {}, RejectReason.MALFORMED_JSON, "top level is str"),
    (
        raw(document(schema="cblrs.detections/2")),
        {},
        RejectReason.WRONG_SCHEMA,
        "cblrs.detections/2",
    ),
    (raw(document(schema="cblrs.tracks/1")), {}, RejectReason.WRONG_SCHEMA, "expected"),
    (raw({**document(schema="v0"), "extra": 1}), {}, RejectReason.WRONG_SCHEMA, "'v0'"),
    (raw(document(schema=None)), {}, RejectReason.MISSING_FIELD, "`schema`"),
    (raw(document(camera=None)), {}, RejectReason.MISSING_FIELD, "`camera`"),
    (raw(document(sequence=None)), {}, RejectReason.MISSING_FIELD, "`sequence`"),
    (raw(document(timestamp=None)), {}, RejectReason.MISSING_FIELD, "`timestamp`"),
    (raw(document(plane=None)), {}, RejectReason.MISSING_FIELD, "`plane`"),
    (raw(document(detections=None)), {}, RejectReason.MISSING_FIELD, "`detections`"),
    (raw(document(detections=[detection(colour=None)])), {}, RejectReason.MISSING_FIELD, "colour"),
    (raw({**document(), "image": "aGVsbG8="}), {}, RejectReason.UNKNOWN_FIELD, "`image`"),
    (
        raw(document(detections=[{**detection(), "crop": [1, 2]}])),
        {},
        RejectReason.UNKNOWN_FIELD,
        "`crop`",
    ),
    (b'{"schema":"cblrs.detections/1","timestamp":NaN}', {}, RejectReason.INVALID_VALUE, "NaN"),
    (raw(document(timestamp=math.inf)), {}, RejectReason.INVALID_VALUE, "NaN and Infinity"),
    (
        raw(document()).replace(b'"timestamp":', b'"timestamp":1e999,"x":'),
        {},
        RejectReason.INVALID_VALUE,
        "out of range",
    ),
    (
        raw(document(detections=[detection(box=[1, 2, math.nan, 4])])),
        {},
        RejectReason.INVALID_VALUE,
        "NaN",
    ),
    (
        raw(document(detections=[detection(box=[5, 2, 3, 4])])),
        {},
        RejectReason.INVALID_VALUE,
        "x_max >= x_min",
    ),
    (
        raw(document(detections=[detection(box=[1, 5, 3, 4])])),
        {},
        RejectReason.INVALID_VALUE,
        "y_max >= y_min",
    ),
    (
        raw(document(detections=[detection(box=[1, 2, 3])])),
        {},
        RejectReason.INVALID_VALUE,
        "length 4",
    ),
    (raw(document(detections=[detection(confidence=1.5)])), {}, RejectReason.INVALID_VALUE, "0..1"),
    (
        raw(document(detections=[detection(confidence="high")])),
        {},
        RejectReason.INVALID_VALUE,
        "`float`",
    ),
    (
        raw(document(detections=[detection(**{"class": "dragon"})])),
        {},
        RejectReason.INVALID_VALUE,
        "dragon",
    ),
    (raw(document(sequence=-1)), {}, RejectReason.INVALID_VALUE, ">= 0"),
    (raw(document(sequence=True)), {}, RejectReason.INVALID_VALUE, "got `bool`"),
    (raw(document(sequence=1.5)), {}, RejectReason.INVALID_VALUE, "got `float`"),
    (raw(document(sequence=2**70)), {}, RejectReason.INVALID_VALUE, "<="),
    (raw(document(frame="7")), {}, RejectReason.INVALID_VALUE, "got `str`"),
    (raw(document(plane=0)), {}, RejectReason.INVALID_VALUE, ">= 1"),
    (raw(document(camera="CVLab1/#")), {}, RejectReason.INVALID_VALUE, "regex"),
    (raw(document(camera="x" * 65)), {}, RejectReason.INVALID_VALUE, "length <= 64"),
    (raw(document(camera="")), {}, RejectReason.INVALID_VALUE, "length >= 1"),
    (raw(document(detections={"class": "person"})), {}, RejectReason.INVALID_VALUE, "`array`"),
    (
        raw(document(detections=[detection()] * (MAX_DETECTIONS + 1))),
        {"max_bytes": 10**6},
        RejectReason.INVALID_VALUE,
        f"length <= {MAX_DETECTIONS}",
    ),
    (b" " * (OVERSIZE + 1), {"max_bytes": OVERSIZE}, RejectReason.OVERSIZED, "exceeds 1024"),
    (
        raw(document(detections=[detection(colour=[1, 2, 65536])])),
        {},
        RejectReason.COLOUR_OUT_OF_RANGE,
        "0..65535",
    ),
    (
        raw(document(detections=[detection(colour=[-1, 2, 1])])),
        {},
        RejectReason.COLOUR_OUT_OF_RANGE,
        "0..65535",
    ),
    (
        raw(document(detections=[detection(colour=[256, 2, 1])])),
        {"bits": 8},
        RejectReason.COLOUR_OUT_OF_RANGE,
        "0..255 (8-bit",
    ),
    (
        raw(document(detections=[detection(colour=[2**64, 2, 1])])),
        {},
        RejectReason.COLOUR_OUT_OF_RANGE,
        "0..65535",
    ),
    (
        raw(document(camera="Ghost")),
        {"known_cameras": {"CVLab1"}},
        RejectReason.UNKNOWN_CAMERA,
        "'Ghost'",
    ),
    (raw(document()), {"topic_camera": "CVLab2"}, RejectReason.TOPIC_MISMATCH, "'CVLab2'"),
    (
        raw(document(timestamp=NOW - 3601)),
        {"max_age_s": 3600},
        RejectReason.TOO_OLD,
        "3601.000 s ago",
    ),
    (
        raw(document(timestamp=NOW + 61)),
        {"max_future_s": 60},
        RejectReason.IN_FUTURE,
        "61.000 s in the future",
    ),
]


@pytest.mark.parametrize(("payload", "options", "reason", "detail"), REJECTIONS)
def test_every_rejection_reason(payload, options, reason, detail):
    with pytest.raises(RejectedMessage) as caught:
        decode_message(payload, now=NOW, **options)
    assert caught.value.reason is reason, caught.value.detail
    assert detail in caught.value.detail
    assert str(caught.value).startswith(reason.value + ": ")


def _plain_verdict(detections: list[dict], bits: int) -> RejectReason | None:
    """The receiver's value rules, one detection and one value at a time (the reference)."""
    if any(not -(2**63) <= value < 2**63 for item in detections for value in item["colour"]):
        return RejectReason.COLOUR_OUT_OF_RANGE  # not even a 64-bit integer: refused first
    for item in detections:
        x_min, y_min, x_max, y_max = item["box"]
        if x_max < x_min or y_max < y_min:
            return RejectReason.INVALID_VALUE
        if not 0 <= item["confidence"] <= 1:
            return RejectReason.INVALID_VALUE
    for item in detections:
        if any(not 0 <= value < 1 << bits for value in item["colour"]):
            return RejectReason.COLOUR_OUT_OF_RANGE
    return None


_edge_floats = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64),
    st.sampled_from([0.0, -0.0, 1.0, 1.0000000000000002, -1e-300, 1.7976931348623157e308]),
)
_edge_colours = st.one_of(
    st.integers(-(2**63), 2**64 - 1),
    st.sampled_from([0, 255, 256, 65535, 65536, -1, 2**53 + 1, 2**63 - 1, 2**63]),
)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.fixed_dictionaries(
            {
                "box": st.lists(_edge_floats, min_size=4, max_size=4),
                "confidence": _edge_floats,
                "colour": st.lists(_edge_colours, min_size=3, max_size=3),
            }
        ),
        max_size=4,
    ),
    st.sampled_from([8, 16]),
)
def test_vectorised_checks_agree_with_the_plain_rules(values, bits):
    detections = [{"class": "person", **item} for item in values]
    payload = raw(document(detections=detections))
    expected = _plain_verdict(detections, bits)
    try:
        message = decode_message(payload, now=NOW, bits=bits)
    except RejectedMessage as error:
        assert error.reason == expected, error
    else:
        assert expected is None
        assert message.xyxy.tolist() == [item["box"] for item in values]
        assert message.confidence.tolist() == [item["confidence"] for item in values]
        assert message.colour.tolist() == [item["colour"] for item in values]
        assert message.colour.dtype == np.int64 and message.xyxy.shape == (len(values), 4)


def test_every_reason_is_covered_by_the_table():
    assert {reason for _, _, reason, _ in REJECTIONS} == set(RejectReason)


def test_topic_plane_mismatch():
    payload = encode_message(make_message(1), plane_id=2)
    with pytest.raises(RejectedMessage, match="plane 2 differs from topic plane 1") as caught:
        decode_message_with_plane(payload, topic_plane=1, now=NOW)
    assert caught.value.reason is RejectReason.TOPIC_MISMATCH


def test_time_window_and_cameras_accept_the_boundaries():
    payload = raw(document(timestamp=NOW - 10))
    assert decode_message(payload, now=NOW, max_age_s=10).timestamp == NOW - 10
    assert decode_message(payload, now=NOW - 20, max_future_s=10).timestamp == NOW - 10
    assert decode_message(payload, now=NOW, max_age_s=math.inf, known_cameras={"CVLab1"})


def test_validation_policy_holds_the_settings():
    policy = ValidationPolicy(known_cameras={"CVLab1"}, bits=8, max_age_s=5, max_bytes=4096)
    assert policy.known_cameras == frozenset({"CVLab1"})
    good = raw(document(detections=[detection(colour=[255, 0, 1])]))
    assert len(policy.decode(good, topic_camera="CVLab1", now=NOW)) == 1
    message, plane = policy.decode_with_plane(good, "CVLab1", NOW, topic_plane=1)
    assert plane == 1 and message.colour.tolist() == [[255, 0, 1]]
    for payload, reason in [
        (
            raw(document(detections=[detection(colour=[256, 0, 1])])),
            RejectReason.COLOUR_OUT_OF_RANGE,
        ),
        (raw(document(camera="CVLab2")), RejectReason.UNKNOWN_CAMERA),
        (raw(document(timestamp=NOW - 6)), RejectReason.TOO_OLD),
        (b" " * 5000, RejectReason.OVERSIZED),
    ]:
        with pytest.raises(RejectedMessage) as caught:
            policy.decode(payload, now=NOW)
        assert caught.value.reason is reason


def test_the_keyword_decoders_are_the_policy():
    """decode_message & co. build one ValidationPolicy from their keywords: same answers."""
    good = raw(document(detections=[detection(colour=[255, 0, 1])]))
    policy = ValidationPolicy(known_cameras={"CVLab1"}, bits=8, max_age_s=5)
    keywords = {"known_cameras": {"CVLab1"}, "bits": 8, "max_age_s": 5}
    assert decode_wire(good, now=NOW, **keywords) == policy.decode_wire(good, now=NOW)
    by_keywords = decode_message(good, now=NOW, **keywords)
    assert by_keywords.colour.tolist() == policy.decode(good, now=NOW).colour.tolist()
    with pytest.raises(RejectedMessage) as caught:
        decode_message(raw(document(timestamp=NOW - 6)), now=NOW, **keywords)
    assert caught.value.reason is RejectReason.TOO_OLD


@pytest.mark.parametrize(
    ("options", "message"),
    [({"bits": 12}, "bits per channel must be 8 or 16"), ({"max_bytes": 0}, "max_bytes > 0")],
)
def test_validation_policy_refuses_bad_settings(options, message):
    with pytest.raises(Exception, match=message):
        ValidationPolicy(**options)


@pytest.mark.parametrize(
    ("change", "reason", "detail"),
    [
        ({"xyxy": np.array([[0, 0, math.nan, 1]])}, RejectReason.INVALID_VALUE, "finite"),
        ({"xyxy": np.array([[5, 0, 1, 1]])}, RejectReason.INVALID_VALUE, "x_max >= x_min"),
        ({"confidence": np.array([2.0])}, RejectReason.INVALID_VALUE, "0..1"),
        ({"class_id": np.array([99])}, RejectReason.INVALID_VALUE, "class ids"),
        ({"colour": np.array([[0, 0, 70000]])}, RejectReason.COLOUR_OUT_OF_RANGE, "0..65535"),
        ({"camera_id": "bad/id"}, RejectReason.INVALID_VALUE, "camera"),
        ({"sequence": -3}, RejectReason.INVALID_VALUE, "sequence"),
        ({"timestamp": math.inf}, RejectReason.INVALID_VALUE, "timestamp"),
    ],
)
def test_encoder_refuses_what_a_receiver_would_reject(change, reason, detail):
    from dataclasses import replace

    message = replace(make_message(1), **change)
    with pytest.raises(RejectedMessage) as caught:
        encode_message(message, plane_id=1)
    assert caught.value.reason is reason
    assert detail in caught.value.detail


def test_encoder_refuses_a_bad_plane_and_too_many_detections():
    with pytest.raises(RejectedMessage, match="plane"):
        encode_message(make_message(1), plane_id=0)
    with pytest.raises(RejectedMessage, match="at most 1000"):
        encode_message(make_message(MAX_DETECTIONS + 1), plane_id=1)


# --------------------------------------------------------------------------- fuzzing

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=12), children, max_size=5)
    ),
    max_leaves=30,
)
FIELDS = ["schema", "camera", "sequence", "timestamp", "frame", "plane", "detections"]
DETECTION_FIELDS = ["class", "confidence", "box", "colour"]


def decode_or_reject(payload: bytes) -> None:
    try:
        decode_message(payload, now=NOW, known_cameras={"CVLab1", "CVLab2"}, topic_camera="CVLab1")
    except RejectedMessage as error:
        assert isinstance(error.reason, RejectReason)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_arbitrary_bytes_only_raise_rejected(payload):
    decode_or_reject(payload)


@settings(max_examples=150, deadline=None)
@given(json_values)
def test_fuzz_arbitrary_json_only_raise_rejected(value):
    decode_or_reject(json.dumps(value).encode())


@settings(max_examples=150, deadline=None)
@given(
    field=st.sampled_from(FIELDS + DETECTION_FIELDS + ["extra"]),
    value=json_values,
    drop=st.booleans(),
)
def test_fuzz_one_field_of_a_valid_message(field, value, drop):
    data = document()
    target = data["detections"][0] if field in DETECTION_FIELDS else data
    if drop and field in target:
        del target[field]
    else:
        target[field] = value
    decode_or_reject(json.dumps(data).encode())


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 300), st.binary(min_size=1, max_size=4))
def test_fuzz_corrupted_valid_payload(position, noise):
    payload = bytearray(encode_message(make_message(2), plane_id=1))
    position = min(position, len(payload) - 1)
    payload[position : position + len(noise)] = noise
    decode_or_reject(bytes(payload))


def test_deep_nesting_is_rejected_not_crashing():
    for payload in [b"[" * 100_000, b'{"a":' * 50_000, b"[" * 2000 + b"]" * 2000]:
        with pytest.raises(RejectedMessage):
            decode_message(payload, now=NOW, max_bytes=10**6)


# --------------------------------------------------------------------------- tracks, status


def make_tracks(count: int) -> Tracks:
    rng = np.random.default_rng(count)
    xyxy = rng.uniform(0, 100, (count, 4))
    if count:
        xyxy[0] = np.nan
    return Tracks(
        frame=np.arange(count),
        timestamp=NOW + np.arange(count) / 10,
        track_id=rng.integers(0, 50, count),
        world_xy=rng.normal(size=(count, 2)),
        camera_id=rng.integers(-1, 7, count),
        xyxy=xyxy,
    )


@pytest.mark.parametrize("count", [0, 1, 10])
def test_tracks_round_trip(count):
    tracks = make_tracks(count)
    payload = encode_tracks(tracks, 4, sequence=9, cameras=["CVLab1", "CVLab2"])
    assert payload.startswith(b'{"schema":"cblrs.tracks/1","plane":4')
    update = decode_tracks(payload)
    assert (update.plane_id, update.sequence, update.cameras) == (4, 9, ("CVLab1", "CVLab2"))
    for name in ("frame", "timestamp", "track_id", "world_xy", "camera_id"):
        assert np.array_equal(getattr(update.tracks, name), getattr(tracks, name)), name
    assert np.array_equal(update.tracks.xyxy, tracks.xyxy, equal_nan=True)


@pytest.mark.parametrize("corrected_from, sent", [(None, None), (NOW, NOW), (-math.inf, 0.0)])
def test_a_correction_says_from_when(corrected_from, sent):
    """Re-tracked rows (late messages) replace those after ``corrected_from``; a correction
    of every row (-inf) is sent from time 0, a plain update carries no such field."""
    payload = encode_tracks(make_tracks(2), 1, timestamp=NOW + 1, corrected_from=corrected_from)
    assert (b'"corrected_from"' in payload) == (sent is not None)
    assert decode_tracks(payload).corrected_from == sent


@pytest.mark.parametrize("corrected_from", [math.nan, math.inf])
def test_a_correction_from_no_time_is_refused(corrected_from):
    with pytest.raises(RejectedMessage, match="corrected time must be finite"):
        encode_tracks(make_tracks(1), 1, corrected_from=corrected_from)


def test_tracks_rejections():
    with pytest.raises(RejectedMessage, match="finite"):
        encode_tracks(Tracks([0], [NOW], [1], [[math.nan, 0.0]]), 1)
    with pytest.raises(RejectedMessage) as caught:
        decode_tracks(raw({"schema": "cblrs.detections/1", "plane": 1}))
    assert caught.value.reason is RejectReason.WRONG_SCHEMA
    with pytest.raises(RejectedMessage) as caught:
        decode_tracks(raw({"schema": "cblrs.tracks/1", "plane": 1, "sequence": 0}))
    assert caught.value.reason is RejectReason.MISSING_FIELD


@settings(max_examples=60, deadline=None)
@given(json_values)
def test_fuzz_tracks_and_status_only_raise_rejected(value):
    for decode in (decode_tracks, decode_status):
        try:
            decode(json.dumps(value).encode())
        except RejectedMessage:
            pass


@pytest.mark.parametrize(
    ("client", "state", "role", "timestamp"),
    [("CVLab1", "online", "camera", NOW), ("matcher1", "offline", "matcher", None)],
)
def test_status_round_trip(client, state, role, timestamp):
    status = decode_status(encode_status(client, state, role=role, timestamp=timestamp))
    assert (status.client, status.state, status.role, status.timestamp) == (
        client,
        state,
        role,
        timestamp,
    )


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"online", RejectReason.MALFORMED_JSON),
        (
            raw({"schema": "cblrs.status/1", "client": "c", "role": "camera", "state": "asleep"}),
            RejectReason.INVALID_VALUE,
        ),
        (
            raw({"client": "c", "role": "camera", "state": "online", "schema": "x"}),
            RejectReason.WRONG_SCHEMA,
        ),
        (
            raw({"schema": "cblrs.status/1", "client": "c", "state": "online"}),
            RejectReason.MISSING_FIELD,
        ),
        (raw({"client": "c", "role": "camera", "state": "online"}), RejectReason.MISSING_FIELD),
    ],
)
def test_status_rejections(payload, reason):
    with pytest.raises(RejectedMessage) as caught:
        decode_status(payload)
    assert caught.value.reason is reason


def test_encode_status_refuses_bad_values():
    with pytest.raises(RejectedMessage, match="state"):
        encode_status("CVLab1", "asleep")  # type: ignore[arg-type]


def test_wire_structs_forbid_unknown_fields():
    from cblrs.runtime.wire import WireDetection, WireMessage

    for struct in (WireMessage, WireDetection):
        assert struct.__struct_config__.forbid_unknown_fields
    # Every string field is bounded or a closed set: nothing can carry an image.
    info = msgspec.inspect.type_info(WireMessage)
    strings = {
        field.name: field.type
        for field in info.fields
        if isinstance(field.type, msgspec.inspect.StrType)
    }
    assert set(strings) == {"schema", "camera"}
    assert strings["camera"].max_length == 64
    assert DETECTIONS_SCHEMA == "cblrs.detections/1"


# --------------------------------------------------------------------------- topics


def test_topic_names():
    assert detections_topic(1, "CVLab1") == "cblrs/1/CVLab1/detections"
    assert status_topic(2, "CVLab1") == "cblrs/2/CVLab1/status"
    assert tracks_topic(3) == "cblrs/3/tracks"
    assert matcher_status_topic(1, "matcher1") == "cblrs/1/matchers/matcher1/status"
    assert detections_filter(1) == "cblrs/1/+/detections"
    assert detections_filter() == "cblrs/+/+/detections"
    assert parse_detections_topic("cblrs/12/cam_7.a-b/detections") == (12, "cam_7.a-b")
    assert parse_status_topic("cblrs/1/CVLab1/status") == (1, "CVLab1")


@pytest.mark.parametrize(
    "camera_id",
    ["", "a/b", "a+b", "a#", "$SYS", "-lead", "x" * 65, "with space", "é", None,
     "CVLab1\n", "CVLab1\r\n", "CVLab1\nCVLab2"],
)
def test_invalid_camera_ids(camera_id):
    with pytest.raises(TopicError, match="not usable in MQTT topics"):
        validate_camera_id(camera_id)


def test_a_trailing_newline_is_not_a_camera_id_on_the_wire():
    # "$" matches before a final newline; the pattern ends with "\Z" (issue 10, item 13).
    document = json.loads(encode_status("CVLab1", "online"))
    document["client"] = "CVLab1\n"
    with pytest.raises(RejectedMessage):
        decode_status(json.dumps(document).encode())
    with pytest.raises(TopicError):
        parse_detections_topic("cblrs/1/CVLab1\n/detections")


@pytest.mark.parametrize("plane_id", [0, -1, 65536, 1.0, True, "1"])
def test_invalid_plane_ids(plane_id):
    with pytest.raises(TopicError, match="plane id"):
        detections_topic(plane_id, "CVLab1")


@pytest.mark.parametrize(
    "topic",
    [
        "cblrs/1/CVLab1/status",
        "cblrs/1/CVLab1/detections/x",
        "other/1/CVLab1/detections",
        "cblrs/01/CVLab1/detections",
        "cblrs/x/CVLab1/detections",
        "cblrs/0/CVLab1/detections",
        "cblrs/1/+/detections",
        "cblrs/1//detections",
        "",
    ],
)
def test_parse_detections_topic_refuses(topic):
    with pytest.raises(TopicError):
        parse_detections_topic(topic)


@settings(max_examples=40, deadline=None)
@given(camera_ids, st.integers(1, 65535))
def test_topic_round_trip(camera_id, plane_id):
    assert parse_detections_topic(detections_topic(plane_id, camera_id)) == (plane_id, camera_id)


@pytest.mark.parametrize(
    ("first", "second", "expected"),
    [
        ("cblrs/1/+/detections", "cblrs/1/+/status", False),
        ("cblrs/1/+/detections", "cblrs/+/CVLab1/detections", True),
        ("cblrs/1/+/detections", "cblrs/#", True),
        ("cblrs/1/tracks", "cblrs/2/tracks", False),
        ("a", "a/#", True),
        ("a/b", "a", False),
        ("+/+", "a/b/c", False),
        ("#", "anything/at/all", True),
        ("a/b", "a/b", True),
    ],
)
def test_filters_overlap(first, second, expected):
    from cblrs.runtime.transport.topics import filters_overlap

    assert filters_overlap(first, second) is expected
    assert filters_overlap(second, first) is expected
