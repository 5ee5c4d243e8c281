"""What one viewer's valid login takes from everyone else on a real `cblrs dashboard`.

Starts `cblrs dashboard --users --db` (the code on PYTHONPATH, or --src) on a stored run of
--rows track rows, logs a viewer in, has it ask for one thing over and over on --connections
connections for --seconds, and meanwhile times `/healthz` (or, with --time-login, the admin's
login) every 0.2 s; prints the median and the worst. Figures in docs/security.md ("What a
viewer could use up"):

    python scripts/dashboard_viewer_load.py --site site.yaml --ask /api/replay/info
    python scripts/dashboard_viewer_load.py --site site.yaml --ask "/api/replay?start=1800000000"
    python scripts/dashboard_viewer_load.py --site site.yaml --ask login --connections 16 \\
        --seconds 20 --time-login
    python scripts/dashboard_viewer_load.py --site site.yaml --ask "/api/places?plane=1" \\
        --time-login

(site.yaml: `cblrs site init WILDTRACK --out site.yaml`; --src /work/main/src runs another
checkout's code.)
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import random
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

VIEWER = ("bob", "bob-viewer-password")
ADMIN = ("alice", "alice-admin-password")


def make_run(path: Path, rows: int) -> None:
    """A matcher database of ``rows`` track rows (20 people, 2 per second of capture)."""
    from cblrs.runtime.matcher.store import RuntimeStore

    RuntimeStore(path).close()
    connection = sqlite3.connect(path)
    generator = random.Random(0)
    with connection:
        connection.executemany(
            "INSERT INTO tracks (frame, timestamp, track_id, x, y, camera, class_id) "
            "VALUES (?, ?, ?, ?, ?, 0, 0)",
            ((i // 20, 1.7e9 + (i // 20) * 0.5, i % 20 + (i // 20000) * 20,
              generator.uniform(-5, 10), generator.uniform(-10, 25)) for i in range(rows)))
    connection.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--site", type=Path, required=True)
    parser.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1] / "src")
    parser.add_argument("--rows", type=int, default=2_000_000)
    parser.add_argument("--ask", default="/api/replay/info",
                        help="a path the viewer GETs, or login (its own right password)")
    parser.add_argument("--connections", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=12.0)
    parser.add_argument("--time-login", action="store_true",
                        help="time the admin's login instead of /healthz")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="viewer-load-"))
    environment = {**os.environ, "PYTHONPATH": str(args.src)}
    users = folder / "users.yaml"
    for (name, password), role in ((VIEWER, "viewer"), (ADMIN, "admin")):
        subprocess.run([sys.executable, "-m", "cblrs.cli.main", "dashboard-users", "add",
                        "--users", str(users), name, "--role", role, "--password-stdin"],
                       input=password + "\n", text=True, env=environment, check=True,
                       capture_output=True)
    database = folder / "run.db"
    make_run(database, args.rows)
    process = subprocess.Popen(
        [sys.executable, "-m", "cblrs.cli.main", "dashboard", "--port", "0", "--site",
         str(args.site), "--users", str(users), "--db", str(database)],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=environment)
    try:
        port = int(process.stdout.readline().split()[2].split(":")[2].split("/")[0])
        return measure(port, args)
    finally:
        process.terminate()
        process.wait(30)


def measure(port: int, args: argparse.Namespace) -> int:
    def request(method, path, body=None, headers=None):
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
        sent = {"Origin": f"http://127.0.0.1:{port}", **(headers or {})}
        if body is not None:
            sent["Content-Type"] = "application/json"
        connection.request(method, path, None if body is None else json.dumps(body), sent)
        response = connection.getresponse()
        data = response.read()
        connection.close()
        return response.status, data, response

    def login(user):
        return request("POST", "/api/login", {"user": user[0], "password": user[1]})

    _, data, response = login(VIEWER)
    session = {"Cookie": response.getheader("set-cookie").split(";")[0],
               "X-CBLRS-Session": json.loads(data)["session"]}
    stop = time.monotonic() + args.seconds
    answers: dict[int, int] = {}

    def ask():
        while time.monotonic() < stop:
            status = (login(VIEWER) if args.ask == "login"
                      else request("GET", args.ask, headers=session))[0]
            answers[status] = answers.get(status, 0) + 1

    threads = [threading.Thread(target=ask) for _ in range(args.connections)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)
    timings = []
    while time.monotonic() < stop - 1.0:
        started = time.perf_counter()
        if args.time_login:
            assert login(ADMIN)[0] == 200
        else:
            request("GET", "/healthz")
        timings.append(time.perf_counter() - started)
        time.sleep(0.2)
    for thread in threads:
        thread.join()
    what = "admin's login" if args.time_login else "/healthz"
    print(f"{what}: {len(timings)} timed, median {statistics.median(timings) * 1000:.0f} ms, "
          f"worst {max(timings) * 1000:.0f} ms; the viewer's {args.ask}: {answers}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
