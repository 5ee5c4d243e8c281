"""Nobody on the admin's address can lock the admin out of a browser the admin uses.

Every local client of a dashboard on loopback is 127.0.0.1 (behind a TLS proxy, every client
is the proxy's address). Before, failed logins locked the address, and a name for the
addresses it failed from: anyone who reached the port, with no login at all, kept the admin
out by failing logins under any names, or under the admin's name with wrong passwords (429
to the admin's right password for as long as they went on). Now a browser that has logged in
as a user carries that user's device cookie, and its logins of that name meet only its own
device's back-off; guessers on the address still meet the name's and the address's.

A real `cblrs dashboard` process with a users file, over real sockets, every client on
127.0.0.1; the back-off lowered by its launcher (``_LAUNCH``: 2 free failures per name, 4
per address, locks of 120 s) so a test needs a few logins.
"""

from __future__ import annotations

import http.client
import json
import subprocess
import sys
from collections.abc import Iterator
from urllib.parse import urlsplit

import pytest
from dashboard_helpers import ADMIN, VIEWER, stop_process

_LAUNCH = (
    "import sys, time\n"
    "from cblrs.dashboard.logins import LoginLimiter\n"
    "LoginLimiter.__init__.__defaults__ = (2, 4, 120.0, 300.0, time.monotonic)\n"
    "from cblrs.cli.main import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


@pytest.fixture
def dashboard(wildtrack_site, users_file) -> Iterator[str]:
    """A `cblrs dashboard --users` with the lowered back-off: its base URL."""
    process = subprocess.Popen(
        [sys.executable, "-c", _LAUNCH, "dashboard", "--port", "0", "--site",
         str(wildtrack_site), "--users", str(users_file)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = process.stdout.readline() if process.stdout else ""
        if not line.startswith("dashboard on "):
            process.kill()
            raise AssertionError(f"the dashboard did not start: {line}"
                                 f"{process.communicate(timeout=10)[1]}")
        yield line.split()[2].split("login?", 1)[0]
    finally:
        stop_process(process)


def login(url: str, user: str, password: str, cookie: str = "") -> tuple[int, str]:
    """POST /api/login from 127.0.0.1 with ``cookie`` (a ``Cookie`` header's value): the
    status and the device cookie the answer sets ("" for none)."""
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    headers = {"Content-Type": "application/json", "Origin": url.rstrip("/")}
    if cookie:
        headers["Cookie"] = cookie
    try:
        connection.request("POST", "/api/login",
                           json.dumps({"user": user, "password": password}), headers)
        response = connection.getresponse()
        response.read()
        device = [value.split(";")[0] for value in response.msg.get_all("set-cookie") or []
                  if value.startswith("cblrs_device=")]
        return response.status, device[0] if device else ""
    finally:
        connection.close()


def test_failures_on_the_admins_address_never_keep_the_admins_browser_out(dashboard):
    status, device = login(dashboard, *ADMIN)  # the admin's browser, some time before
    assert status == 200

    # Someone else on 127.0.0.1, with no login: the admin's name with wrong passwords ...
    guesses = [login(dashboard, ADMIN[0], f"guess-password-{i}")[0] for i in range(4)]
    assert guesses == [401, 401, 401, 429], guesses  # the name locked for this address
    # ... and other names, until the address is locked as well
    others = [login(dashboard, f"mallory-{i}", "guess-password-x")[0] for i in range(3)]
    assert others == [401, 401, 429], others
    assert login(dashboard, VIEWER[0], "guess-password-y")[0] == 429  # guessing stays slowed

    # The admin's browser logs in at once (before: 429 for as long as the failures went on).
    status, kept = login(dashboard, *ADMIN, cookie=device)
    assert status == 200, "failures of others on the admin's address locked the admin out"
    assert kept == device  # the same device: its own back-off is not reset elsewhere

    # The guesser has no device of the admin's: the right password without one, with a
    # made-up one, or with the admin's device for another name, still meets the locks.
    assert login(dashboard, *ADMIN)[0] == 429
    forged = device[:-1] + ("b" if device.endswith("a") else "a")
    assert login(dashboard, *ADMIN, cookie=forged)[0] == 429
    assert login(dashboard, *VIEWER, cookie=device)[0] == 429

    # Guessing with the admin's device (a caught cookie) meets the device's own back-off.
    with_device = [login(dashboard, ADMIN[0], f"guess-password-{i}", cookie=device)[0]
                   for i in range(4)]
    assert with_device == [401, 401, 401, 429], with_device


def test_a_device_has_its_own_back_off_and_is_bound_to_its_user_and_password():
    from cblrs.dashboard.logins import LoginLimiter, device_cookie, device_of

    cookie = device_cookie("alice", "scrypt$hash-of-alice")
    nonce = device_of(cookie, "alice", "scrypt$hash-of-alice")
    assert nonce is not None and cookie.startswith(nonce + ".")
    assert device_of(cookie, "bob", "scrypt$hash-of-alice") is None  # another name
    assert device_of(cookie, "alice", "scrypt$new-hash") is None  # a new password ends it
    assert device_of(cookie, "alice", "") is None  # no password: no devices
    assert device_of(nonce + ".0", "alice", "scrypt$hash-of-alice") is None

    now = [1000.0]
    limiter = LoginLimiter(free_per_user=2, free_per_client=3, base_s=1.0, max_s=8.0,
                           clock=lambda: now[0])
    for index in range(6):  # the address and the name locked by others' failures
        limiter.failed("alice" if index % 2 else f"x{index}", "127.0.0.1")
    assert limiter.wait_s("alice", "127.0.0.1") > 0
    assert limiter.wait_s("alice", "127.0.0.1", nonce) == 0  # the device is not
    for _ in range(2):
        limiter.failed("alice", "127.0.0.1", nonce)
    assert limiter.wait_s("alice", "127.0.0.1", nonce) == 0  # free failures
    limiter.failed("alice", "127.0.0.1", nonce)
    assert limiter.wait_s("alice", "10.0.0.9", nonce) == 1.0  # locked, from any address
    assert limiter.wait_s("alice", "10.0.0.9") == 0  # the device's failures are its own
    limiter.succeeded("alice", "127.0.0.1", nonce)
    assert limiter.wait_s("alice", "127.0.0.1", nonce) == 0
    # the device's right password says nothing of the others on its address: their lock stays
    for _ in range(3):
        limiter.failed("alice", "10.1.1.1")
    limiter.succeeded("alice", "10.1.1.1", nonce)
    assert limiter.wait_s("alice", "10.1.1.1") > 0
    assert limiter.wait_s("alice", "10.1.1.1", nonce) == 0
