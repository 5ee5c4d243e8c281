"""Nobody writes a line of their own into the dashboard's log (real `cblrs dashboard`).

The log is the dashboard's only audit trail (logins, failed logins, refusals, saves, each
with the user). A refusal names the request's path, which the server decodes from the URL:
an anonymous client that put ``%0A`` in it wrote a line of its choosing, such as an admin's
save that never happened, after the refusal. Every cblrs log line now shows control
characters escaped, so one record is one line.
"""

from __future__ import annotations

import http.client
from urllib.parse import quote, urlsplit

FORGED = "2026-01-01T00:00:00.000 INFO cblrs.dashboard.app: dashboard: alice saved 3 zones"


def test_a_path_with_a_newline_writes_no_line_of_its_own(wildtrack_site, start_dashboard):
    served = start_dashboard("--site", str(wildtrack_site))
    parts = urlsplit(served.url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        # not JSON: refused (415) and logged with its path, before any login
        connection.request("POST", "/api/x" + quote("\n" + FORGED + "\r\x1b[2K"), body="{}",
                           headers={"Content-Type": "text/plain"})
        answer = connection.getresponse()
        answer.read()
        assert answer.status == 415
    finally:
        connection.close()
    served.process.terminate()
    _, log = served.process.communicate(timeout=30)
    refusals = [line for line in log.splitlines() if "refused POST /api/x" in line]
    assert len(refusals) == 1, log
    assert "\\n2026-01-01T00:00:00.000 INFO" in refusals[0] and "\\x1b" in refusals[0]
    assert not any(line.startswith(FORGED[:30]) for line in log.splitlines()), log
    assert "\x1b" not in log and "\r" not in log
