"""The plane lease of a NATS transport (:class:`_NatsLease`, a part of
:class:`~cblrs.runtime.transport.nats_transport.NatsTransport`).

A key (``plane-<plane>``, ``<site>.plane-<plane>``) with a time to live in the replicated
key-value bucket ``cblrs_leases``: taken on connect (refused, one sentence, while another
client holds it), renewed every third of its TTL, deleted on a clean close. While it is not
renewed deliveries are held; lost to another holder, deliveries stop and ``on_failure`` is
called. A write into the key that is no lease record (a forged reply) is written over.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any

from cblrs.runtime.transport.nats_streams import _NatsStreams
from cblrs.runtime.transport.nats_subjects import LEASE_BUCKET
from cblrs.runtime.transport.protocol import TransportError

logger = logging.getLogger("cblrs.runtime.transport.nats_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""

LEASE_UNANSWERED_S = 30.0
"""How long a lease is asked for again while JetStream does not answer (seconds)."""

_NO_PEERS_YET = 10005
"""JetStream's "no suitable peers for placement": what a replicated bucket gets while its
cluster is still forming (not every peer known to the meta leader yet); asked again like an
unanswered request."""


class _NatsLease(_NatsStreams):
    """Taking, renewing, releasing and losing the plane lease of a NATS transport."""

    async def _acquire_lease(self) -> None:
        # optional extra: pip install cblrs[nats]
        from nats.errors import NoRespondersError
        from nats.errors import TimeoutError as NatsTimeoutError
        from nats.js.api import KeyValueConfig
        from nats.js.errors import (
            APIError,
            BucketNotFoundError,
            KeyNotFoundError,
            KeyWrongLastSequenceError,
            NoStreamResponseError,
            ServiceUnavailableError,
        )

        lease = self.lease
        assert lease is not None
        # JetStream may not answer for a moment (a cluster that has just started and not yet
        # elected its meta leader, or electing the bucket's leader): asked again for this
        # long, then the error is the answer. Opening the bucket waits too: a matcher started
        # with its cluster failed there at once ("nats: timeout", 1 run in 15 at load 10).
        unanswered = (NoStreamResponseError, NoRespondersError, NatsTimeoutError,
                      ServiceUnavailableError)
        waited_s = max(lease.wait_s, LEASE_UNANSWERED_S)
        unanswered_until = time.monotonic() + waited_s
        said = False

        async def not_yet(error: Exception, what: str, managing: bool = False) -> None:
            """Wait a moment to ask again, or raise: refused (``managing``: a call only the
            backbone's admin may make), or unanswered for too long."""
            nonlocal said
            if self.refused_subjects:  # not unanswered: refused (the servers said so)
                if managing:
                    raise self._refused_management(what, error) from None
                raise TransportError(f"cannot {what}: {self._denial_or(error)}.") from None
            if time.monotonic() >= unanswered_until:
                raise TransportError(
                    f"cannot {what}: JetStream did not answer for {waited_s:g} s "
                    f"({error or type(error).__name__})."
                ) from None
            if not said:
                said = True
                logger.warning("%s: JetStream does not answer yet (%s); asking again for "
                               "the lease %s", self.client_id, error or type(error).__name__,
                               lease.key)
            await asyncio.sleep(0.5)

        while True:
            try:
                kv = await self._js.key_value(LEASE_BUCKET)
                break
            except BucketNotFoundError:
                if not self.settings.manages:
                    raise TransportError(
                        f"the NATS lease bucket {LEASE_BUCKET} does not exist; the backbone's "
                        "admin creates it (cblrs matcher --prepare with the admin's login)."
                    ) from None
                try:
                    kv = await self._js.create_key_value(KeyValueConfig(
                        bucket=LEASE_BUCKET, history=1, ttl=lease.ttl_s, direct=True,
                        replicas=await self._replicas()))
                    break
                except unanswered as error:
                    await not_yet(error, f"create the lease bucket {LEASE_BUCKET}", True)
                except APIError as error:
                    if error.err_code != _NO_PEERS_YET:
                        raise self._refused_management(
                            f"create the lease bucket {LEASE_BUCKET}", error) from None
                    await not_yet(error, f"create the lease bucket {LEASE_BUCKET}", True)
                except Exception as error:
                    raise self._refused_management(f"create the lease bucket {LEASE_BUCKET}",
                                                   error) from None
            except unanswered as error:
                await not_yet(error, f"open the NATS lease bucket {LEASE_BUCKET}")
            except Exception as error:
                raise TransportError(
                    f"cannot open the NATS lease bucket {LEASE_BUCKET}: "
                    f"{self._denial_or(error)}."
                ) from None
        self._lease_kv = kv
        value = json.dumps({"holder": self.lease_holder, "since": time.time()}).encode()
        self._lease_value = value
        deadline = time.monotonic() + lease.wait_s
        while True:
            try:
                self._lease_revision = await kv.create(lease.key, value)
                break
            except unanswered as error:
                await not_yet(error, f"take the lease {lease.key} of "
                                     f"{lease.what or 'the plane'}")
            except KeyNotFoundError:
                # nats-py's create() looks the key up after finding it taken; the holder's
                # lease expired in between: ask again at once.
                await asyncio.sleep(0.05)
                continue
            except KeyWrongLastSequenceError:
                forged = await self._forged_lease(kv)
                if forged is not None:
                    self._lease_revision = await kv.update(lease.key, value, last=forged)
                    break
                holder, age = await self._lease_holder(kv)
                if time.monotonic() >= deadline:
                    raise TransportError(
                        f"{lease.what or lease.key} is already served by {holder} (lease renewed "
                        f"{age:.0f} s ago); stop that matcher first, or give --lease-wait longer "
                        f"than the lease's {lease.ttl_s:g} s time to live to take over once it "
                        "has died"
                    ) from None
                await asyncio.sleep(min(0.5, max(0.05, deadline - time.monotonic())))
            except Exception as error:
                raise TransportError(
                    f"cannot take the lease {lease.key} of {lease.what or 'the plane'}: "
                    f"{self._denial_or(error)}."
                ) from None
        logger.info("%s: holds %s", self.client_id, lease.key)
        self._lease_task = asyncio.get_running_loop().create_task(self._renew_lease(value))

    async def _forged_lease(self, kv: Any) -> int | None:
        """The revision of the lease key if what it holds is no lease record, else None.

        nats-server checks a publish's subject against the login's permissions, never its
        reply subject: any login that may publish into a stream can name the lease key as the
        reply, and JetStream writes its acknowledgement (``{"stream": ..., "seq": ...}``) there.
        Such a write claims nothing; the holder (or a newcomer) writes over it.
        """
        try:
            entry = await kv.get(self.lease.key)  # type: ignore[union-attr]
        except Exception:  # no entry (expired or deleted): nothing forged
            return None
        try:
            record = json.loads(entry.value or b"")
        except ValueError:
            record = None
        if isinstance(record, dict) and isinstance(record.get("holder"), str):
            return None
        logger.warning("%s: %s held a write that is no lease record (%.80r), such as a "
                       "forged reply; writing over it", self.client_id,
                       self.lease.key, entry.value)
        return entry.revision

    async def _lease_holder(self, kv: Any) -> tuple[str, float]:
        try:
            entry = await kv.get(self.lease.key)  # type: ignore[union-attr]
            holder = json.loads(entry.value or b"{}").get("holder", "another matcher")
            created = entry.created
            age = time.time() - created.timestamp() if created is not None else 0.0
            return holder, age
        except Exception:
            return "another matcher", 0.0

    async def _renew_lease(self, value: bytes) -> None:
        # optional extra: pip install cblrs[nats]
        from nats.js.errors import KeyWrongLastSequenceError

        lease = self.lease
        assert lease is not None
        last_renewal = time.monotonic()
        while not self._closing:
            await asyncio.sleep(lease.ttl_s / 3)
            try:
                try:
                    self._lease_revision = await self._lease_kv.update(
                        lease.key, value, last=self._lease_revision)
                except KeyWrongLastSequenceError:
                    # Our entry expired while the cluster was out of reach: take it again
                    # only if nobody has written the key since (expected last revision 0).
                    self._lease_revision = await self._lease_kv.update(lease.key, value, last=0)
                    logger.warning("%s: %s had expired while out of reach; taken again",
                                   self.client_id, lease.key)
                last_renewal = time.monotonic()
                self._resume_deliveries()
            except KeyWrongLastSequenceError:
                forged = await self._forged_lease(self._lease_kv)
                if forged is None:
                    self._lose_lease(
                        f"{lease.what or lease.key} was taken over by another matcher")
                    return
                try:
                    self._lease_revision = await self._lease_kv.update(
                        lease.key, value, last=forged)
                except KeyWrongLastSequenceError:
                    continue  # written again meanwhile: looked at again at the next renewal
                last_renewal = time.monotonic()
                self._resume_deliveries()
            except asyncio.CancelledError:
                raise
            except Exception as error:
                if time.monotonic() - last_renewal > lease.ttl_s and not self._lease_paused:
                    # Another matcher could hold the plane now: hold deliveries until the
                    # lease is ours again (or lost).
                    self._lease_paused = True
                    logger.warning("%s: lease not renewed for %.0f s (%s); holding deliveries",
                                   self.client_id, lease.ttl_s, error or type(error).__name__)

    def _resume_deliveries(self) -> None:
        if not self._lease_paused:
            return
        self._lease_paused = False
        held, self._held = self._held, []
        logger.info("%s: lease renewed; delivering %d held messages", self.client_id, len(held))
        for item in held:
            self._handlers.dispatch(item)

    def _lose_lease(self, reason: str) -> None:
        self.lease_lost = True
        self._acks.clear()
        self._held.clear()
        logger.error("%s: lost the lease: %s; no more deliveries", self.client_id, reason)
        if self.on_failure is not None:
            self.on_failure(f"lost the plane lease: {reason}.")

    async def _release_lease(self) -> None:
        """Delete the lease key so that the next matcher takes the plane at once.

        A renewal cancelled by the close may have been stored without its new revision
        reaching this client: the delete's expected revision is then stale and refused. The
        key is read again and deleted at its revision if it still holds this client's record
        (else the plane would stay held for the lease's TTL: a restarted matcher without
        --lease-wait was refused, and its cameras never confirmed; CI failed once so)."""
        kv, key = self._lease_kv, self.lease.key  # type: ignore[union-attr]
        try:
            await kv.delete(key, last=self._lease_revision)
            return
        except Exception as error:
            logger.debug("lease release at revision %d failed: %s", self._lease_revision, error)
        try:
            entry = await kv.get(key)
            if entry.value == self._lease_value:
                await kv.delete(key, last=entry.revision)
        except Exception as error:  # it expires anyway
            logger.debug("lease release failed: %s", error)
