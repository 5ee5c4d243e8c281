"""Runtime: the paper's Fig. 4 as services talking through a broker.

The runtime is split into rooms, one per role (each a subpackage):

* :mod:`cblrs.runtime.wire` — the message schemas (JSON, validated with msgspec): detections,
  tracks, status;
* :mod:`cblrs.runtime.transport` — how services talk: the :class:`Transport` protocol
  (``transport.protocol``), its implementations (``inprocess``: an embedded broker for
  tests and the offline pipeline; ``mqtt_transport``: MQTT 5 with paho; ``nats_transport``:
  NATS JetStream), the topic layout ``cblrs/<plane>/<camera>/...`` (``topics``) and the
  rate-limited log lines they share with the services (``rate_limited``);
* :mod:`cblrs.runtime.broker` — the backbone's servers and their secrets: Mosquitto's
  configuration (``mosquitto_config``: users, ACL, TLS, persistence) and process
  (``mosquitto``), NATS servers as child processes (``nats_server``) and NATS users,
  permissions and TLS (``nats_auth``), passwords and certificates (``credentials``);
* :mod:`cblrs.runtime.camera` — the edge camera node (``camera_node``, ``cblrs camera``),
  where its detections come from (``sources``) and its disk spool (``spool``);
* :mod:`cblrs.runtime.matcher` — the matcher service (``matcher_service``, ``cblrs
  matcher``) and what it stands on: its SQLite store (``store``), the ordering of received
  messages into windows (``ordering``, also used by the offline pipeline), the
  confirmations it sends the cameras (``confirmations``), the one-matcher-per-plane lease
  (``lease``), the tracker's process (``tracker_process``) and its re-tracking of late
  messages (``retrack``), the database's retention (``retention``), the cameras' views
  (``views``) and its Prometheus metrics and health endpoints (``metrics``);
* :mod:`cblrs.runtime.outputs` — what is made from the tracks while they flow: online
  analytics (``online_analytics``, ``analytics_store``, ``analytics_service``), their
  events and live summary on the wire (``events``), the cross-plane linker
  (``linker_service``, ``linker_store``) and alerts (``alert_service``).

The names listed in ``__all__`` can be imported from :mod:`cblrs.runtime` itself.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# The names below are imported on first use (PEP 562), as in `cblrs`: a module that needs one
# room of the runtime (the offline pipeline imports only `cblrs.runtime.matcher.ordering`) does not
# pay for the transports, the broker and paho at start-up.
_LAZY = {
    "BrokerError": "cblrs.runtime.broker.mosquitto_config",
    "BrokerFiles": "cblrs.runtime.broker.mosquitto_config",
    "Delivery": "cblrs.runtime.transport.protocol",
    "InProcessBroker": "cblrs.runtime.transport.inprocess",
    "InProcessTransport": "cblrs.runtime.transport.inprocess",
    "LeaseError": "cblrs.runtime.matcher.lease",
    "MosquittoProcess": "cblrs.runtime.broker.mosquitto_config",
    "MqttSettings": "cblrs.runtime.transport.mqtt_transport",
    "MqttTransport": "cblrs.runtime.transport.mqtt_transport",
    "PlaneLease": "cblrs.runtime.matcher.lease",
    "RejectReason": "cblrs.runtime.wire",
    "RejectedMessage": "cblrs.runtime.wire",
    "RetainedTable": "cblrs.runtime.matcher.retention",
    "RetentionPolicy": "cblrs.runtime.matcher.retention",
    "Spool": "cblrs.runtime.camera.spool",
    "SpoolError": "cblrs.runtime.camera.spool",
    "Status": "cblrs.runtime.wire",
    "TopicError": "cblrs.runtime.transport.topics",
    "TracksUpdate": "cblrs.runtime.wire",
    "Transport": "cblrs.runtime.transport.protocol",
    "TransportError": "cblrs.runtime.transport.protocol",
    "ValidationPolicy": "cblrs.runtime.wire",
    "Will": "cblrs.runtime.transport.protocol",
    "apply_retention": "cblrs.runtime.matcher.retention",
    "decode_message": "cblrs.runtime.wire",
    "decode_message_with_plane": "cblrs.runtime.wire",
    "decode_status": "cblrs.runtime.wire",
    "decode_tracks": "cblrs.runtime.wire",
    "detections_filter": "cblrs.runtime.transport.topics",
    "detections_topic": "cblrs.runtime.transport.topics",
    "encode_message": "cblrs.runtime.wire",
    "encode_status": "cblrs.runtime.wire",
    "encode_tracks": "cblrs.runtime.wire",
    "free_port": "cblrs.runtime.broker.mosquitto_config",
    "matcher_status_topic": "cblrs.runtime.transport.topics",
    "parse_detections_topic": "cblrs.runtime.transport.topics",
    "status_topic": "cblrs.runtime.transport.topics",
    "tracks_topic": "cblrs.runtime.transport.topics",
    "validate_camera_id": "cblrs.runtime.transport.topics",
    "write_broker_config": "cblrs.runtime.broker.mosquitto_config",
}

if TYPE_CHECKING:
    from cblrs.runtime.broker.mosquitto_config import (
        BrokerError,
        BrokerFiles,
        MosquittoProcess,
        free_port,
        write_broker_config,
    )
    from cblrs.runtime.camera.spool import Spool, SpoolError
    from cblrs.runtime.matcher.lease import LeaseError, PlaneLease
    from cblrs.runtime.matcher.retention import RetainedTable, RetentionPolicy, apply_retention
    from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
    from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
    from cblrs.runtime.transport.protocol import Delivery, Transport, TransportError, Will
    from cblrs.runtime.transport.topics import (
        TopicError,
        detections_filter,
        detections_topic,
        matcher_status_topic,
        parse_detections_topic,
        status_topic,
        tracks_topic,
        validate_camera_id,
    )
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
