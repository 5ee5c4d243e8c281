"""A paho-mqtt client that reads its socket in large chunks.

paho reads each incoming packet with several ``recv`` calls: its type byte, each byte of its
remaining length, then its body, one system call each, in its network thread, which holds
the interpreter lock (GIL) in between. A matcher receiving thousands of messages a second
spends a good part of its receiving thread there (with 50 cameras, about 15 % of the matcher
service's CPU in ``recv``). :class:`BufferedClient` reads up to :data:`READ_SIZE` bytes at
once and serves paho's small reads from them.

Everything else is paho's: its packet parsing (which keeps a packet read in part between
calls) and its event loop. The one thing the loop must not miss: it waits for the socket
to be readable before reading, and bytes already read into the buffer no longer make the
socket readable, so :meth:`BufferedClient.loop_read` goes on reading packets until the
buffer is empty. Bytes read from one socket are never served after paho has replaced it (a
reconnection): the buffer remembers its socket.
"""

from __future__ import annotations

from typing import Any

import paho.mqtt
import paho.mqtt.client as mqtt

READ_SIZE = 65536
"""Bytes asked of the socket per ``recv`` (TLS returns at most one record, 16 KiB)."""


def buffered_reads_supported() -> bool:
    """Whether this paho has the private reading methods :class:`BufferedClient` builds on.

    Checked against paho-mqtt 2.1 and 2.2; another major version, or one without them, gets
    paho's own client (correct, only slower).
    """
    return (
        str(getattr(paho.mqtt, "__version__", "")).startswith("2.")
        and callable(getattr(mqtt.Client, "_sock_recv", None))
        and callable(getattr(mqtt.Client, "loop_read", None))
    )


class BufferedClient(mqtt.Client):
    """:class:`paho.mqtt.client.Client` with buffered socket reads (see the module)."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._read_buffer = b""
        self._read_at = 0
        self._read_socket: Any = None

    def _sock_recv(self, bufsize: int) -> bytes:
        if self._read_at >= len(self._read_buffer) or self._read_socket is not self._sock:
            self._read_buffer, self._read_at = b"", 0
            socket = self._sock
            data = super()._sock_recv(READ_SIZE)  # raises as paho expects when nothing came
            if len(data) <= bufsize:  # all of it asked for (or b"": the connection closed)
                return data
            self._read_buffer, self._read_socket = data, socket
        start = self._read_at
        self._read_at = start + bufsize
        return self._read_buffer[start : self._read_at]

    def buffered(self) -> int:
        """Bytes read from the current socket and not yet handed to paho."""
        if self._read_socket is not self._sock:
            return 0
        return max(0, len(self._read_buffer) - self._read_at)

    def loop_read(self, max_packets: int = 1) -> mqtt.MQTTErrorCode:
        result = super().loop_read(max_packets)
        # paho stops after max_packets; what is buffered would wait for the next bytes.
        while result == mqtt.MQTTErrorCode.MQTT_ERR_SUCCESS and self.buffered():
            result = super().loop_read(max_packets)
        return result
