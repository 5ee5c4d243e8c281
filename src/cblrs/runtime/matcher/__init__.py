"""The matcher service (``cblrs matcher``) and what it stands on.

* :mod:`cblrs.runtime.matcher.matcher_service` — the service: receives detections, stores
  them, tracks, publishes tracks and confirmations; its state in
  :mod:`~cblrs.runtime.matcher.matcher_state`, its receiver thread in
  :mod:`~cblrs.runtime.matcher.matcher_receiver`, its releaser and collector threads in
  :mod:`~cblrs.runtime.matcher.matcher_releaser`;
* :mod:`cblrs.runtime.matcher.store` — its SQLite database (inbox, tracks, state), with
  its tables (:mod:`~cblrs.runtime.matcher.store_schema`), rows
  (:mod:`~cblrs.runtime.matcher.store_rows`) and file (:mod:`~cblrs.runtime.matcher.store_file`:
  checks, private mode, writers' lock);
* :mod:`cblrs.runtime.matcher.ordering` — which received messages go to the tracker together
  (also used by the offline pipeline);
* :mod:`cblrs.runtime.matcher.confirmations` — end-to-end confirmations to the cameras;
* :mod:`cblrs.runtime.matcher.lease` — one matcher per plane;
* :mod:`cblrs.runtime.matcher.tracker_process` — the tracker in a process of its own;
* :mod:`cblrs.runtime.matcher.retrack` — re-tracking after a late message;
* :mod:`cblrs.runtime.matcher.retention` — how much history the database keeps;
* :mod:`cblrs.runtime.matcher.views` — where each camera sees the ground;
* :mod:`cblrs.runtime.matcher.metrics` — Prometheus metrics, health and readiness.
"""
