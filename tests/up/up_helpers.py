"""Helpers of the ``cblrs up`` tests: a small live site (two WILDTRACK cameras, 40 annotated
frames each) and a runner of the real command."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

CAMERAS = ("CVLab1", "CVLab2")
PER_CAMERA = 40  # annotated frames 0, 5, ..., 195
RUN_AS = ["--run-as", "root"] if os.geteuid() == 0 else []
"""As root, Mosquitto would switch to its own user, which cannot enter pytest's private
temporary folders (the runtime tests do the same)."""


def small_site_text(wildtrack: Path, frames: str = "0:195") -> str:
    rows = []
    for name in CAMERAS:
        rows.append(
            f"  - {{name: {name}, image_size: [1920, 1080], calibration: {{file: {wildtrack}, "
            f"camera: {name}}},\n     source: {{kind: dataset, path: {wildtrack}, "
            f'frames: "{frames}"}}}}'
        )
    return "\n".join([
        "version: 1", "name: small-live",
        "planes:", "  - {id: 1, name: ground, origin: [-5.0, -11.0], size: [16.0, 40.0]}",
        "cameras:", *rows,
        "places:", "  lines:", "    - {name: middle, start: [-2.5, 6.0], end: [8.5, 6.0]}", ""])


def up_command(site: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", "up", str(site), "--out", str(out),
            "--broker-port", "0", "--dashboard-port", "0", "--json", *RUN_AS, *extra]


ENVIRONMENT = {**os.environ, "PYTHONUNBUFFERED": "1"}


def run_up(site: Path, out: Path, *extra: str, timeout: float = 120,
           environment: dict | None = None) -> tuple[int, dict | None, str]:
    """Run ``cblrs up`` to its end: exit code, its JSON summary (None if none), stderr."""
    result = subprocess.run(up_command(site, out, *extra), capture_output=True, text=True,
                            timeout=timeout, env=environment or ENVIRONMENT)
    summary = json.loads(result.stdout) if result.stdout.strip().startswith("{") else None
    return result.returncode, summary, result.stderr


def first_tracks_on_the_map(url: str, timeout: float) -> list:
    """Log in with the dashboard's link as its login page does (the link's token posted to
    /api/login: a session cookie and its page token), and read its live stream until a track
    update with tracks in it arrives; its rows."""
    item = first_on_the_stream(url, lambda item: item.get("type") == "tracks" and item["rows"],
                               timeout, "no tracks on the map")
    return item["rows"]


def first_on_the_stream(url: str, wanted, timeout: float, what: str = "nothing wanted") -> dict:
    """Log in with the dashboard's link (as :func:`first_tracks_on_the_map`) and read its live
    stream until an item for which ``wanted(item)`` holds arrives; that item."""
    import urllib.request

    base = url.split("/login")[0]
    login = urllib.request.urlopen(urllib.request.Request(
        base + "/api/login", data=json.dumps({"token": url.split("token=", 1)[1]}).encode(),
        headers={"Content-Type": "application/json", "Origin": base}), timeout=10)
    session = {"Cookie": login.headers["Set-Cookie"].split(";")[0],
               "X-CBLRS-Session": json.loads(login.read())["session"]}
    stream = urllib.request.urlopen(urllib.request.Request(base + "/api/stream",
                                                           headers=session), timeout=timeout)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            line = stream.readline().decode()
            if line.startswith("data: "):
                item = json.loads(line[len("data: "):])
                if wanted(item):
                    return item
    finally:
        stream.close()
    raise AssertionError(f"{what} within {timeout} s")


def processes() -> list[tuple[int, int, str]]:
    """Every live process now: (pid, process group, command line), from ``ps``; zombies are
    left out (they have ended: whoever adopted them reaps them, or not, as pid 1 does in
    some containers)."""
    listing = subprocess.run(["ps", "-ww", "-eo", "pid=,pgid=,stat=,args="],
                             capture_output=True, text=True, check=True).stdout
    rows = []
    for line in listing.splitlines():
        pid, group, state, *args = line.split(None, 3)
        if not state.startswith("Z"):
            rows.append((int(pid), int(group), args[0] if args else ""))
    return rows


def site_groups(out: Path) -> set[int]:
    """The process groups of a running site's children: each runs in a group of its own,
    with what it starts (the matcher's tracker process); their command lines name ``out``."""
    return {group for pid, group, args in processes()
            if str(out) in args and " up " not in args}


def left_in(groups: set[int]) -> list[str]:
    """The processes still alive in ``groups``."""
    return [f"{pid} {args}" for pid, group, args in processes() if group in groups]
