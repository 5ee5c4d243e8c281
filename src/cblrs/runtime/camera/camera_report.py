"""What a camera node's run did: :class:`CameraReport`, the counts
:meth:`~cblrs.runtime.camera.camera_node.CameraNode.run` returns (frames, messages, deliveries,
confirmations, resends, drops by reason, a refusal)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class CameraReport:
    """What a camera node did.

    Attributes:
        camera_id: the camera.
        plane_id: the plane it published for.
        frames: frames read from the source.
        messages: messages produced (one per frame, unless a frame was dropped).
        detections: boxes published.
        located: boxes whose target pixel saw a plane (colour B != 0).
        bytes: payload bytes produced.
        first_sequence: sequence number of the first message.
        next_sequence: sequence number the next message would have had.
        elapsed_s: wall time from the first to the last message produced, seconds.
        acknowledged: broker acknowledgements received (re-sends count again).
        confirmed: messages the matcher confirmed as stored.
        rejected_by_matcher: messages the matcher confirmed as rejected, by reason.
        refused_by_broker: publishes the broker refused.
        refusal: the broker's first refusal as one sentence, or None.
        resent: messages sent again (see the module docstring).
        boxes_rejected: boxes dropped before sending, by reason.
        frames_too_large: frames dropped because their message exceeded the size limit.
        frames_skipped: frames skipped because their image file was unusable, by reason
            (``empty``, ``truncated``, ``undecodable``; each logged).
        unconfirmed: messages still in the spool at the end (sent again on the next start).
        dropped_from_spool: messages the full spool dropped (ever, for a spool file).
        flushed: every message of the spool acknowledged by the broker at the end (none
            waiting, none refused).
        confirmed_all: the spool is empty: the matcher confirmed everything.
        epoch: the epoch added to recorded timestamps, seconds since the Unix epoch.
    """

    camera_id: str
    plane_id: int
    frames: int = 0
    messages: int = 0
    detections: int = 0
    located: int = 0
    bytes: int = 0
    first_sequence: int = 0
    next_sequence: int = 0
    elapsed_s: float = 0.0
    acknowledged: int = 0
    confirmed: int = 0
    rejected_by_matcher: dict[str, int] = field(default_factory=dict)
    refused_by_broker: int = 0
    refusal: str | None = None
    resent: int = 0
    boxes_rejected: dict[str, int] = field(default_factory=dict)
    frames_too_large: int = 0
    frames_skipped: dict[str, int] = field(default_factory=dict)
    unconfirmed: int = 0
    dropped_from_spool: int = 0
    flushed: bool = False
    confirmed_all: bool = False
    epoch: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        data = {key: value for key, value in self.__dict__.items() if key != "extra"}
        data.update(self.extra)
        data["messages_per_s"] = self.messages / self.elapsed_s if self.elapsed_s > 0 else None
        return data
