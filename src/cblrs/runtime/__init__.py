"""Runtime: the paper's Fig. 4 as services talking through a broker.

* :mod:`cblrs.runtime.wire` — message schemas (JSON, validated with msgspec);
* :mod:`cblrs.runtime.topics` — MQTT topic layout ``cblrs/<plane>/<camera>/...``;
* :mod:`cblrs.runtime.transport` — in-process broker and MQTT 5 (paho) transports;
* :mod:`cblrs.runtime.broker` — Mosquitto configuration (users, ACL, TLS) and process;
* :mod:`cblrs.runtime.spool`, :mod:`cblrs.runtime.confirmations` — a camera keeps each message
  on disk until the matcher confirms it stored it;
* :mod:`cblrs.runtime.lease` — one matcher per plane;
* :mod:`cblrs.runtime.retention` — how much history the matcher's database keeps.
"""

from __future__ import annotations

from cblrs.runtime.broker import (
    BrokerError,
    BrokerFiles,
    MosquittoProcess,
    free_port,
    write_broker_config,
)
from cblrs.runtime.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.lease import LeaseError, PlaneLease
from cblrs.runtime.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.retention import RetainedTable, RetentionPolicy, apply_retention
from cblrs.runtime.spool import Spool, SpoolError
from cblrs.runtime.topics import (
    TopicError,
    detections_filter,
    detections_topic,
    matcher_status_topic,
    parse_detections_topic,
    status_topic,
    tracks_topic,
    validate_camera_id,
)
from cblrs.runtime.transport import Delivery, Transport, TransportError, Will
from cblrs.runtime.wire import (
    RejectedMessage,
    RejectReason,
    Status,
    TracksUpdate,
    ValidationPolicy,
    decode_message,
    decode_message_with_plane,
    decode_status,
    decode_tracks,
    encode_message,
    encode_status,
    encode_tracks,
)

__all__ = [
    "BrokerError",
    "BrokerFiles",
    "Delivery",
    "InProcessBroker",
    "InProcessTransport",
    "LeaseError",
    "MosquittoProcess",
    "MqttSettings",
    "MqttTransport",
    "PlaneLease",
    "RejectReason",
    "RejectedMessage",
    "RetainedTable",
    "RetentionPolicy",
    "Spool",
    "SpoolError",
    "Status",
    "TopicError",
    "TracksUpdate",
    "Transport",
    "TransportError",
    "ValidationPolicy",
    "Will",
    "apply_retention",
    "decode_message",
    "decode_message_with_plane",
    "decode_status",
    "decode_tracks",
    "detections_filter",
    "detections_topic",
    "encode_message",
    "encode_status",
    "encode_tracks",
    "free_port",
    "matcher_status_topic",
    "parse_detections_topic",
    "status_topic",
    "tracks_topic",
    "validate_camera_id",
    "write_broker_config",
]
