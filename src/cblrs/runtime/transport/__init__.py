"""How the runtime's services talk: the transport protocol, its implementations and the topics.

* :mod:`cblrs.runtime.transport.protocol` — :class:`~cblrs.runtime.transport.protocol.Transport`
  and the types every transport shares (deliveries, wills, errors);
* :mod:`cblrs.runtime.transport.inprocess` — an embedded broker in one process (tests, the
  offline pipeline);
* :mod:`cblrs.runtime.transport.mqtt_transport` — MQTT 5 (paho-mqtt); its settings in
  :mod:`~cblrs.runtime.transport.mqtt_settings`, its parts
  :mod:`~cblrs.runtime.transport.mqtt_publisher` and
  :mod:`~cblrs.runtime.transport.mqtt_subscriptions` (with their shared state in
  :mod:`~cblrs.runtime.transport.mqtt_state`);
* :mod:`cblrs.runtime.transport.nats_transport` — NATS with JetStream;
  its parts :mod:`~cblrs.runtime.transport.nats_streams`,
  :mod:`~cblrs.runtime.transport.nats_consumer`, :mod:`~cblrs.runtime.transport.nats_publisher`
  and :mod:`~cblrs.runtime.transport.nats_lease` (with their shared state in
  :mod:`~cblrs.runtime.transport.nats_state`);
* :mod:`cblrs.runtime.transport.topics` — the topic layout ``cblrs/<plane>/<camera>/...``;
* :mod:`cblrs.runtime.transport.rate_limited` — log lines that repeat at most once every few
  seconds.
"""
