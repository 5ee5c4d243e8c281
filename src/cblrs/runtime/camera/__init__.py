"""The edge camera (``cblrs camera``): its node, its sources and its spool.

* :mod:`cblrs.runtime.camera.camera_node` — the node: reads a source, publishes detections
  and status, resends what the matcher has not confirmed; its state in
  :mod:`~cblrs.runtime.camera.camera_state`, its delivery side (results, confirmations,
  resends) in :mod:`~cblrs.runtime.camera.camera_delivery`, its counts in
  :mod:`~cblrs.runtime.camera.camera_report`;
* :mod:`cblrs.runtime.camera.sources` — where the detections come from (files, scenes,
  video through a detector);
* :mod:`cblrs.runtime.camera.spool` — the disk spool that keeps each message until the
  matcher confirms it stored it.
"""
