"""Who may read the matcher's /metrics (``cblrs matcher --http``): with a token, only a scrape
that carries it (bearer, or the basic-auth password Prometheus sends); health checks from
loopback stay open; beyond loopback the server needs a token, and the command says so."""

from __future__ import annotations

import base64
import subprocess
import sys
import urllib.error
import urllib.request

import pytest

from cblrs.runtime.matcher.metrics import (
    MetricsServer,
    MetricsServerError,
    check_exposure,
    is_loopback_host,
    request_allowed,
)

TOKEN = "s3cret-metrics-token-0123456789"


def fetch(url: str, authorization: str | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url, headers={"Authorization": authorization}
                                     if authorization else {})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


def basic(user: str, password: str) -> str:
    return "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()


@pytest.fixture
def server():
    started = MetricsServer(("127.0.0.1", 0), lambda: b"cblrs_live_tracks 3\n",
                            lambda: (True, ""), lambda: (False, "not connected"),
                            token=TOKEN).start()
    yield started
    started.close()


def test_metrics_need_the_token(server):
    url = f"{server.url}/metrics"
    status, headers, body = fetch(url)
    assert status == 401 and b"cblrs_live_tracks" not in body
    assert headers["WWW-Authenticate"].startswith("Basic")
    for wrong in (f"Bearer {TOKEN}x", f"Bearer {TOKEN[:-1]}", basic("prometheus", "nope"),
                  "Bearer ", f"Token {TOKEN}", "Basic !!!"):
        assert fetch(url, wrong)[0] == 401, wrong
    for right in (f"Bearer {TOKEN}", basic("prometheus", TOKEN), basic("", TOKEN)):
        status, headers, body = fetch(url, right)
        assert status == 200 and body == b"cblrs_live_tracks 3\n", right
        assert headers["X-Content-Type-Options"] == "nosniff"
    # Health checks from this machine need no token (and say what they say).
    assert fetch(f"{server.url}/healthz")[0] == 200
    status, _, body = fetch(f"{server.url}/readyz")
    assert status == 503 and b"not connected" in body


def test_who_may_ask_what():
    assert request_allowed("/metrics", "10.1.2.3", "", None)  # no token: loopback-only server
    assert not request_allowed("/metrics", "127.0.0.1", "", TOKEN)
    assert request_allowed("/healthz", "127.0.0.1", "", TOKEN)
    assert request_allowed("/readyz", "::1", "", TOKEN)
    assert not request_allowed("/healthz", "10.1.2.3", "", TOKEN)
    assert request_allowed("/healthz", "10.1.2.3", f"Bearer {TOKEN}", TOKEN)
    assert all(is_loopback_host(host) for host in ("127.0.0.1", "127.5.6.7", "::1",
                                                   "localhost"))
    assert not any(is_loopback_host(host) for host in ("0.0.0.0", "::", "10.0.0.1",
                                                       "no-such-host.invalid"))


def test_beyond_loopback_needs_a_token():
    with pytest.raises(MetricsServerError, match="needs --http-token-file"):
        check_exposure("0.0.0.0", None)
    with pytest.raises(MetricsServerError, match="needs --http-token-file"):
        MetricsServer(("0.0.0.0", 0), lambda: b"", lambda: (True, ""), lambda: (True, ""))
    with pytest.raises(MetricsServerError, match="at least 16"):
        MetricsServer(("127.0.0.1", 0), lambda: b"", lambda: (True, ""), lambda: (True, ""),
                      token="short")
    check_exposure("127.0.0.1", None)
    check_exposure("0.0.0.0", TOKEN)


def test_the_matcher_command_refuses_open_metrics_beyond_loopback(wildtrack_root, tmp_path):
    """One sentence and exit 2, before anything connects or a database is made."""
    from cblrs.cli.main import main

    site = tmp_path / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(site)]) == 0
    short = tmp_path / "short.token"
    short.write_text("tiny\n")
    cases = [
        ([], "needs --http-token-file"),
        (["--http-token-file", str(short)], "at least 16"),
        (["--http-token-file", str(tmp_path / "missing.token")], "cannot read"),
    ]
    for extra, words in cases:
        result = subprocess.run(
            [sys.executable, "-m", "cblrs.cli.main", "matcher", "--site", str(site), "--db",
             str(tmp_path / "plane1.db"), "--http", "0.0.0.0:0", *extra],
            capture_output=True, text=True, timeout=120)
        lines = result.stderr.strip().splitlines()
        assert result.returncode in (1, 2) and len(lines) == 1, result.stderr
        assert words in lines[0] and "Traceback" not in result.stderr, lines
        assert not (tmp_path / "plane1.db").exists()
