"""The JetStream streams of a NATS transport: finding or creating a plane's streams, and
their limits (:class:`_NatsStreams`, a part of
:class:`~cblrs.runtime.transport.nats_transport.NatsTransport`).

Two streams per plane, each with its own leader: ``CBLRS_P<plane>`` (detections and camera
status) and ``CBLRS_P<plane>_TRACKS`` (track updates, analytics events, alerts); a detections
stream caps every camera subject (:meth:`_NatsStreams._camera_limits`). A deployment made
before per-plane streams keeps its one ``CBLRS`` stream (:meth:`_NatsStreams._resolve_stream`).
Only a client that manages streams (an admin) creates or changes them.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import replace
from typing import Any

from cblrs.runtime.transport.nats_state import _NatsState
from cblrs.runtime.transport.nats_subjects import (
    LEGACY_DETECTIONS_STREAM,
    LEGACY_TRACKS_STREAM,
    detections_stream,
    stream_subjects,
    subject_root,
    tracks_stream,
)
from cblrs.runtime.transport.protocol import TransportError

logger = logging.getLogger("cblrs.runtime.transport.nats_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""


class _NatsStreams(_NatsState):
    """The streams part of a NATS transport (and the sentences for refused requests)."""

    async def _replicas(self) -> int:
        if self.settings.replicas is not None:
            return self.settings.replicas
        info = self._nc._server_info or {}
        return 3 if info.get("cluster") else 1

    async def _resolve_stream(self, kind: str, plane_id: int) -> str:
        """The stream that stores a plane's ``kind`` ("detections" or "tracks").

        Its own stream (created if missing when this client manages streams); but a
        deployment made by cblrs before per-plane streams has one ``CBLRS`` stream (and
        ``CBLRS_TRACKS``) for every plane, which keeps serving it (with a warning once):
        the server refuses a new stream whose subjects overlap an existing one's.
        """
        maker = detections_stream if kind == "detections" else tracks_stream
        name = maker(plane_id, self._site)
        if name in self._streams:
            return self._streams[name]
        lock = self._stream_locks.setdefault(name, asyncio.Lock())
        async with lock:
            if name not in self._streams:
                self._streams[name] = await self._find_or_create(name, kind, plane_id)
        return self._streams[name]

    async def _find_or_create(self, name: str, kind: str, plane_id: int) -> str:
        # optional extra: pip install cblrs[nats]
        from nats.js.api import RetentionPolicy, StorageType, StreamConfig
        from nats.js.errors import BadRequestError, NotFoundError

        if not self.settings.manages:
            return name  # runtime logins may not look streams up; the admin made them
        try:
            info = await self._js.stream_info(name)
            await self._add_subjects(info, stream_subjects(name, plane_id, self._site), kind)
            return name
        except NotFoundError:
            pass
        except Exception as error:
            raise self._refused_management(f"read the stream {name}", error) from None
        if self._site is None:
            legacy = LEGACY_DETECTIONS_STREAM if kind == "detections" else LEGACY_TRACKS_STREAM
            try:
                info = await self._js.stream_info(legacy)
                if kind == "tracks":
                    await self._add_subjects(info, [f"{subject_root(None)}.*.alerts"], kind)
                logger.warning(
                    "%s: the NATS stream %s made by an older cblrs holds every plane's %s; "
                    "using it (to give each plane its own stream %s, see docs/security.md, "
                    "'Per-plane streams')", self.client_id, legacy, kind, name)
                return legacy
            except NotFoundError:
                pass
        config = StreamConfig(
            name=name, subjects=stream_subjects(name, plane_id, self._site),
            retention=RetentionPolicy.LIMITS, storage=StorageType.FILE,
            max_age=self.settings.retention_s, duplicate_window=self.settings.duplicate_window_s,
            num_replicas=await self._replicas(), allow_direct=True,
        )
        if kind == "detections":
            config = replace(config, **self._camera_limits())
        try:
            await self._js.add_stream(config)
            logger.info("%s: created the NATS stream %s", self.client_id, name)
        except BadRequestError as error:
            if "already in use" not in str(error) and "already exists" not in str(error):
                raise TransportError(f"cannot create the NATS stream {name}: {error}.") from None
        except Exception as error:
            raise self._refused_management(f"create the stream {name}", error) from None
        return name

    def _camera_limits(self) -> dict[str, Any]:
        """A detections stream's limits per camera subject: at most
        ``messages_per_camera`` messages of at most ``max_msg_bytes`` each, and a publish
        beyond is refused (discard new, per subject) rather than dropping anyone's stored
        messages, so a camera that floods fills its own subject, never another camera's."""
        from nats.js.api import DiscardPolicy

        return {"max_msgs_per_subject": self.settings.messages_per_camera,
                "discard": DiscardPolicy.NEW, "discard_new_per_subject": True,
                "max_msg_size": self.settings.max_msg_bytes}

    async def _add_subjects(self, info: Any, subjects: list[str], kind: str) -> None:
        """Give an existing stream the subjects it lacks (one made before alerts were
        stored lacks ``<root>.<plane>.alerts``) and, a plane's detections stream, the
        per-camera limits (one made before them has none)."""
        current = list(info.config.subjects or [])
        missing = [subject for subject in subjects if subject not in current]
        changes: dict[str, Any] = {}
        if missing:
            changes["subjects"] = current + missing
        if kind == "detections":
            limits = self._camera_limits()
            if any(getattr(info.config, key) != value for key, value in limits.items()):
                changes.update(limits)
        if not changes:
            return
        await self._js.update_stream(replace(info.config, **changes))
        logger.info("%s: the NATS stream %s now %s", self.client_id, info.config.name,
                    "; ".join(f"{key} {value}" for key, value in changes.items()))

    def _refused_management(self, what: str, error: Exception) -> TransportError:
        """One sentence for a management call that failed (refused, or no answer)."""
        if self.refused_subjects:
            return TransportError(
                f"{self.client_id}: cannot {what}: the login {self.settings.username} may not "
                f"use {self.refused_subjects[-1]}; only the backbone's admin may (cblrs matcher "
                "--prepare with the admin's login)."
            )
        return TransportError(f"{self.client_id}: cannot {what}: "
                              f"{str(error) or type(error).__name__}.")

    def _denial_or(self, error: Exception) -> str:
        """Why a request failed: the permission the servers refused, if they did."""
        if self.refused_subjects:
            return f"the login {self.settings.username} may not use {self.refused_subjects[-1]}"
        return str(error) or type(error).__name__
