"""What the runtime makes from the tracks while they flow: analytics, links, alerts.

* :mod:`cblrs.runtime.outputs.online_analytics` — the analytics counted in the matcher as the
  tracker commits;
* :mod:`cblrs.runtime.outputs.analytics_store` — their tables (event outbox, counters, state)
  in the matcher's database;
* :mod:`cblrs.runtime.outputs.analytics_service` — publishing events, the live summary and
  metrics;
* :mod:`cblrs.runtime.outputs.events` — events and live summary on the wire;
* :mod:`cblrs.runtime.outputs.linker_service`, :mod:`cblrs.runtime.outputs.linker_store` —
  the site's linker (``cblrs linker``: global ids across planes) and its database;
* :mod:`cblrs.runtime.outputs.alert_service` — the site's alert rules, run by the matcher
  service.
"""
