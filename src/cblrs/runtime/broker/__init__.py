"""The backbone's servers: their configuration, processes and credentials.

* :mod:`cblrs.runtime.broker.mosquitto_config` — Mosquitto's configuration (users, ACL, TLS,
  persistence), written by ``cblrs broker-config``;
* :mod:`cblrs.runtime.broker.mosquitto` — a Mosquitto child process (tests, benchmarks, demos);
* :mod:`cblrs.runtime.broker.nats_server` — NATS servers with JetStream as child processes
  (one node or a cluster);
* :mod:`cblrs.runtime.broker.nats_auth` — NATS users, permissions and TLS (the NATS side of
  ``cblrs broker-config``);
* :mod:`cblrs.runtime.broker.credentials` — passwords, hashes, TLS certificates and the
  per-client folders they are handed out in.
"""
