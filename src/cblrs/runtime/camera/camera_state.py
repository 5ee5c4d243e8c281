"""The state of a :class:`~cblrs.runtime.camera.camera_node.CameraNode`: its settings, its
spool and sequence numbers, and the events and counters its threads share.

The delivery part (:mod:`~cblrs.runtime.camera.camera_delivery`: broker results, matcher
confirmations and status, resends) is a mixin of this class; the run (capture, pump, pacing)
is :class:`~cblrs.runtime.camera.camera_node.CameraNode` itself.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from cblrs.reference import ReferenceImage
from cblrs.runtime.camera.spool import Spool
from cblrs.runtime.transport.topics import (
    detections_topic,
    status_topic,
    validate_camera_id,
)
from cblrs.runtime.wire import (
    DEFAULT_MAX_BYTES,
)
from cblrs.targeting import TargetingPosition

logger = logging.getLogger("cblrs.runtime.camera.camera_node")
"""The node's logger: its parts log under the one name."""


__all__ = ["_CameraState"]  # in the API reference: the attributes of CameraNode are set here


class _CameraState:
    """What a camera node holds (its constructor: see
    :class:`~cblrs.runtime.camera.camera_node.CameraNode`)."""

    stop: Callable[[], None]  # CameraNode.stop: a refusal stops the node
    _spool: Spool  # set by CameraNode.run for the run

    def __init__(
        self,
        transport: Any,
        plane_id: int,
        camera_id: str,
        reference: ReferenceImage,
        *,
        realtime: bool = False,
        speed: float = 1.0,
        epoch: float | None = None,
        first_sequence: int = 0,
        targeting: dict[str, TargetingPosition] | None = None,
        drop_hidden_feet: bool = False,
        flush_timeout_s: float = 30.0,
        confirm_timeout_s: float = 0.0,
        spool: Spool | None = None,
        resend_after_s: float = 30.0,
        window: int = 1000,
        max_bytes: int = DEFAULT_MAX_BYTES,
        clear_retained: bool = False,
        clock: Callable[[], float] = time.time,
    ):
        validate_camera_id(camera_id)
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}.")
        self.transport = transport
        self.plane_id = int(plane_id)
        self.camera_id = camera_id
        self.reference = reference
        self.realtime = realtime
        self.speed = float(speed)
        self.epoch = epoch
        self.first_sequence = int(first_sequence)
        self.targeting = targeting
        self.drop_hidden_feet = bool(drop_hidden_feet)
        self.flush_timeout_s = float(flush_timeout_s)
        self.confirm_timeout_s = float(confirm_timeout_s)
        self.spool = spool
        self.resend_after_s = float(resend_after_s)
        self.window = max(1, int(window))
        self.max_bytes = int(max_bytes)
        self.clear_retained = clear_retained
        self._clock = clock
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._pump_stop = threading.Event()
        self._counts: Counter[str] = Counter()
        self._rejected_by_matcher: Counter[str] = Counter()
        self._refusal: str | None = None
        self._matcher_online = False
        self._last_confirmation = -float("inf")
        self._resend_wait = self.resend_after_s
        self._lock = threading.Lock()
        self._online_published = False
        self._announce_when_connected = False
        self._done = False
        self._flushed = False
        self._answers = True
        self._marks_resends = False
        self._fresh: set[int] = set()  # produced in this run and not yet handed over
        self._resends = 0
        self._run_token = f"{int(time.time() * 1000):x}"
        self.topic = detections_topic(self.plane_id, camera_id)
        self.status_topic = status_topic(self.plane_id, camera_id)
