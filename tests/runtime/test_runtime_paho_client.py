"""The buffered paho client hands paho every packet it has read, and only its socket's.

paho's event loop reads only when the socket is readable; bytes already taken into the
client's buffer do not make it readable, so a packet left there would wait for the next
bytes to arrive. The client runs here on one end of a socket pair, the test writing MQTT
PUBLISH packets (QoS 0, MQTT 3.1.1) into the other end.
"""

from __future__ import annotations

import socket
import struct

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from cblrs.runtime.transport.paho_client import BufferedClient

TOPIC = "cblrs/1/cam1/detections"


def publish_packet(payload: bytes) -> bytes:
    topic = TOPIC.encode()
    body = struct.pack("!H", len(topic)) + topic + payload
    length, remaining = b"", len(body)
    while True:
        byte, remaining = remaining % 128, remaining // 128
        length += bytes([byte | (128 if remaining else 0)])
        if not remaining:
            return b"\x30" + length + body


def client_on_socket_pair():
    client = BufferedClient(callback_api_version=CallbackAPIVersion.VERSION2,
                            protocol=mqtt.MQTTv311)
    received: list[bytes] = []
    client.on_message = lambda _client, _userdata, message: received.append(message.payload)
    ours, theirs = socket.socketpair()
    ours.setblocking(False)
    client._sock = ours  # what connect() would have opened
    return client, received, theirs


def test_every_packet_read_at_once_is_handled_in_one_loop_read():
    client, received, broker = client_on_socket_pair()
    payloads = [bytes([index]) * 300 for index in range(20)]
    broker.sendall(b"".join(publish_packet(payload) for payload in payloads))
    assert client.loop_read() == mqtt.MQTTErrorCode.MQTT_ERR_SUCCESS
    assert received == payloads
    assert client.buffered() == 0


def test_a_packet_split_between_reads_is_completed_by_the_next_bytes():
    client, received, broker = client_on_socket_pair()
    stream = publish_packet(b"a" * 200) + publish_packet(b"b" * 200)
    broker.sendall(stream[:250])  # the first packet and a part of the second
    client.loop_read()
    assert received == [b"a" * 200]
    broker.sendall(stream[250:])
    client.loop_read()
    assert received == [b"a" * 200, b"b" * 200]


def test_bytes_read_from_a_replaced_socket_are_not_served():
    client, _, broker = client_on_socket_pair()
    broker.sendall(publish_packet(b"old" * 50) * 3)
    assert client._sock_recv(1) == b"\x30"  # paho took one byte; the rest is buffered
    assert client.buffered() > 0
    # A reconnection replaces the socket: the old one's bytes must not reach the new session.
    ours, theirs = socket.socketpair()
    ours.setblocking(False)
    client._sock = ours
    assert client.buffered() == 0
    theirs.sendall(b"\x20\x02\x00\x00")  # CONNACK
    assert client._sock_recv(4) == b"\x20\x02\x00\x00"


def test_the_transport_uses_the_buffered_client_only_where_paho_has_what_it_builds_on(monkeypatch):
    from cblrs.runtime.transport import paho_client

    assert paho_client.buffered_reads_supported()  # the paho this project pins
    monkeypatch.setattr(paho_client.paho.mqtt, "__version__", "3.0.0")
    assert not paho_client.buffered_reads_supported()
