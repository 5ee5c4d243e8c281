"""A camera's ``source:`` in the site file: what ``cblrs up`` runs for it (see docs/up.md).

``kind`` is ``dataset`` (a WILDTRACK or MultiviewX folder's annotated boxes), ``detections``
(a MOT or AI City file), ``video`` (a file), ``images`` (a folder) or ``url`` (a live stream);
the last three run a ``detector``. :class:`SourceModel` is part of
:class:`cblrs.site.schema.CameraModel`; :func:`cblrs.up.plan.source_options` turns it into
``cblrs camera`` options.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, model_validator


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _colour(value: Any) -> list[float]:
    what = "expected [R, G, B]: three numbers from 0 to 255"
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__") or len(value) != 3:
        raise ValueError(what)
    if not all(isinstance(item, int | float) and not isinstance(item, bool)
               and math.isfinite(item) and 0 <= item <= 255 for item in value):
        raise ValueError(what)
    return [float(item) for item in value]


MAX_FPS = 1000.0


def _frame_rate(value: Any) -> float:
    """A camera's frame rate: a finite number of frames per second in (0, 1000]."""
    what = f"expected a frame rate: frames per second, a number above 0 and at most {MAX_FPS:g}"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what}, e.g. 10 (got {value!r})")
    if not (math.isfinite(value) and 0 < value <= MAX_FPS):
        raise ValueError(f"{what} (got {value!r})")
    return float(value)


FrameRate = Annotated[float, BeforeValidator(_frame_rate)]
"""A frame rate key of the site file (a camera's ``fps``, the site's ``camera_fps``)."""


class DetectorModel(_Strict):
    """The detector a camera runs on its frames (``cblrs camera --detector``)."""

    kind: Literal["onnx", "yolo", "blob"] = "onnx"
    model: str | None = None  # onnx: a local .onnx file (relative to the site file)
    weights: str | None = None  # yolo: a local .pt file
    confidence: float | None = Field(default=None, ge=0, le=1)
    colour: Annotated[list[float], BeforeValidator(_colour)] | None = None  # blob: R, G, B

    @model_validator(mode="after")
    def _needs(self) -> DetectorModel:
        if self.kind == "onnx" and not self.model:
            raise ValueError("an onnx detector needs model: a local .onnx file")
        if self.kind == "yolo" and not self.weights:
            raise ValueError("a yolo detector needs weights: a local .pt file")
        return self


def _frame_range(text: str | None) -> str | None:
    first, separator, last = (text or "").partition(":")
    if text is not None and not ((separator and (first + last).isdigit()) or text == ":"):
        raise ValueError(f"frames {text!r} must be FIRST:LAST frame numbers, e.g. 0:195")
    return text


SOURCE_KINDS = ("dataset", "images", "video", "url", "detections")


class SourceModel(_Strict):
    """Where a camera's detections come from when ``cblrs up`` runs it.

    ``dataset`` replays a WILDTRACK or MultiviewX folder's annotated boxes, ``detections`` a
    MOT or AI City file (needs ``fps``), ``video`` and ``images`` a file or a folder through
    ``detector``, ``url`` a live stream (RTSP, HTTP, a device number) through ``detector``.
    Paths are relative to the site file. Replays are paced by their timestamps (``realtime``,
    default true); a live ``url`` always is.
    """

    kind: Literal["dataset", "images", "video", "url", "detections"]
    path: str | None = None
    url: str | None = None
    frames: Annotated[str | None, AfterValidator(_frame_range)] = None
    fps: FrameRate | None = None
    format: Literal["mot", "aicity"] = "mot"
    detector: DetectorModel | None = None
    realtime: bool = True

    @model_validator(mode="after")
    def _complete(self) -> SourceModel:
        if self.kind == "url":
            if not self.url:
                raise ValueError("a url source needs url: (rtsp://..., http://... or a device)")
            if self.path is not None:
                raise ValueError("a url source takes url:, not path:")
        else:
            if not self.path:
                raise ValueError(f"a {self.kind} source needs path:")
            if self.url is not None:
                raise ValueError(f"a {self.kind} source takes path:, not url:")
        if self.kind in ("dataset", "detections") and self.detector is not None:
            raise ValueError(f"a {self.kind} source has its boxes already; it takes no detector")
        if self.kind in ("images", "video", "url") and self.detector is None:
            raise ValueError(
                f"a {self.kind} source needs detector: {{kind: onnx, model: M.onnx}} "
                "(or yolo with weights, or blob)"
            )
        if self.kind == "detections" and self.fps is None:
            raise ValueError("a detections source needs fps: (the frame rate of its numbers)")
        if self.kind == "url" and self.frames is not None:
            raise ValueError("a url source is live: it takes no frames:")
        return self
