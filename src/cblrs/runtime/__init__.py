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

import importlib
from typing import TYPE_CHECKING, Any

# The names below are imported on first use (PEP 562), as in `cblrs`: a module that needs one
# room of the runtime (the offline pipeline imports only `cblrs.runtime.ordering`) does not
# pay for the transports, the broker and paho at start-up.
_LAZY = {
    "BrokerError": "cblrs.runtime.broker",
    "BrokerFiles": "cblrs.runtime.broker",
    "Delivery": "cblrs.runtime.transport",
    "InProcessBroker": "cblrs.runtime.inprocess",
    "InProcessTransport": "cblrs.runtime.inprocess",
    "LeaseError": "cblrs.runtime.lease",
    "MosquittoProcess": "cblrs.runtime.broker",
    "MqttSettings": "cblrs.runtime.mqtt_transport",
    "MqttTransport": "cblrs.runtime.mqtt_transport",
    "PlaneLease": "cblrs.runtime.lease",
    "RejectReason": "cblrs.runtime.wire",
    "RejectedMessage": "cblrs.runtime.wire",
    "RetainedTable": "cblrs.runtime.retention",
    "RetentionPolicy": "cblrs.runtime.retention",
    "Spool": "cblrs.runtime.spool",
    "SpoolError": "cblrs.runtime.spool",
    "Status": "cblrs.runtime.wire",
    "TopicError": "cblrs.runtime.topics",
    "TracksUpdate": "cblrs.runtime.wire",
    "Transport": "cblrs.runtime.transport",
    "TransportError": "cblrs.runtime.transport",
    "ValidationPolicy": "cblrs.runtime.wire",
    "Will": "cblrs.runtime.transport",
    "apply_retention": "cblrs.runtime.retention",
    "decode_message": "cblrs.runtime.wire",
    "decode_message_with_plane": "cblrs.runtime.wire",
    "decode_status": "cblrs.runtime.wire",
    "decode_tracks": "cblrs.runtime.wire",
    "detections_filter": "cblrs.runtime.topics",
    "detections_topic": "cblrs.runtime.topics",
    "encode_message": "cblrs.runtime.wire",
    "encode_status": "cblrs.runtime.wire",
    "encode_tracks": "cblrs.runtime.wire",
    "free_port": "cblrs.runtime.broker",
    "matcher_status_topic": "cblrs.runtime.topics",
    "parse_detections_topic": "cblrs.runtime.topics",
    "status_topic": "cblrs.runtime.topics",
    "tracks_topic": "cblrs.runtime.topics",
    "validate_camera_id": "cblrs.runtime.topics",
    "write_broker_config": "cblrs.runtime.broker",
}

if TYPE_CHECKING:
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


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'cblrs.runtime' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


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
