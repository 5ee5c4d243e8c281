"""A webhook receiver cannot bounce the matcher's requests elsewhere.

urllib follows redirects on its own: a receiver (or whoever answers at its address) replying
``302 Location: http://127.0.0.1:.../`` made the matcher request an address of the
matcher's own network (the cloud's metadata service, an admin port on loopback), with the
alert's signature headers, and counted the alert delivered. A redirect is now a refusal:
not followed, not retried, logged with its status.
"""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from cblrs.alerts import WebhookSender
from cblrs.alerts.rules import WebhookModel

SECRET = b"correct horse battery staple"


class Server:
    """A real HTTP server on a free loopback port: records every request, answers
    ``status`` (with ``Location: location`` when given)."""

    def __init__(self, status: int = 200, location: str | None = None):
        self.requests: list[tuple[str, dict]] = []
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def answer(self):
                length = int(self.headers.get("Content-Length") or 0)
                self.rfile.read(length)
                owner.requests.append((self.command, dict(self.headers)))
                self.send_response(status)
                if location is not None:
                    self.send_header("Location", location)
                self.send_header("Content-Length", "0")
                self.end_headers()

            do_GET = do_POST = do_PUT = answer

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def inside():
    server = Server()  # what the receiver points at: the matcher's own network
    yield server
    server.close()


@pytest.mark.parametrize("status", [301, 302, 303, 307, 308])
def test_a_redirect_is_not_followed(inside, status):
    inside.requests.clear()
    receiver = Server(status, location=inside.url + "latest/meta-data/")
    try:
        sender = WebhookSender(WebhookModel(name="ops", url=receiver.url, secret_env="X",
                                            retries=3, backoff_s=0.01), SECRET)
        result = sender.send({"episode": "crowd/market/1", "state": "fired"})
    finally:
        receiver.close()
    assert inside.requests == []
    assert not result.delivered and result.attempts == 1 and result.status == status
    assert "redirect" in (result.error or "")
    assert [command for command, _ in receiver.requests] == ["POST"]
