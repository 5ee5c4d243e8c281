"""How long from ``cblrs up SITE`` to the first tracks on the live map (docs/up.md).

Starts ``cblrs up`` (a state folder of its own), logs in with the dashboard's link as a browser
would, reads the page's live stream (``/api/stream``, what the map draws) until a track update
with tracks in it arrives, then stops the site with SIGINT (Ctrl-C) and times that too::

    python scripts/up_time_to_map.py sites/wildtrack-live.yaml --out /tmp/up-demo
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request


def first_tracks(url: str, timeout: float) -> list:
    """Rows of the first track update with tracks, read from the dashboard's live stream."""
    # As the login link's page does: its token posted to /api/login, whose answer holds the
    # session's page token; every request carries it beside the session cookie.
    base = url.split("/login")[0]
    login = urllib.request.urlopen(urllib.request.Request(
        base + "/api/login", data=json.dumps({"token": url.split("token=", 1)[1]}).encode(),
        headers={"Content-Type": "application/json", "Origin": base}), timeout=10)
    session = {"Cookie": login.headers["Set-Cookie"].split(";")[0],
               "X-CBLRS-Session": json.loads(login.read())["session"]}
    stream = urllib.request.urlopen(urllib.request.Request(base + "/api/stream",
                                                           headers=session), timeout=timeout)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = stream.readline().decode()
        if line.startswith("data: "):
            item = json.loads(line[len("data: "):])
            if item.get("type") == "tracks" and item["rows"]:
                return item["rows"]
    raise SystemExit(f"no tracks on the map within {timeout} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("site")
    parser.add_argument("--out", required=True, help="cblrs up's state folder")
    parser.add_argument("--timeout", type=float, default=120.0)
    args = parser.parse_args()
    started = time.monotonic()
    process = subprocess.Popen(
        [sys.executable, "-m", "cblrs.cli.main", "up", args.site, "--out", args.out, "--quiet",
         "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = process.stderr.readline()
        while line and not line.startswith("dashboard: "):
            line = process.stderr.readline()
        if not line:
            raise SystemExit(f"cblrs up printed no dashboard link: {process.communicate()[1]}")
        link_s = time.monotonic() - started
        rows = first_tracks(line.split(" ", 1)[1].strip(), args.timeout)
        map_s = time.monotonic() - started
        process.send_signal(signal.SIGINT)
        sent = time.monotonic()
        process.communicate(timeout=120)
        stop_s = time.monotonic() - sent
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    print(f"login link after {link_s:.1f} s; first {len(rows)} tracks on the map after "
          f"{map_s:.1f} s; Ctrl-C stopped everything in {stop_s:.1f} s (exit "
          f"{process.returncode}); load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
