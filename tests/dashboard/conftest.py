"""Fixtures for the dashboard tests: a headless Chromium page, Mosquitto brokers with users,
the WILDTRACK site, a dashboard users file (an admin and a viewer, made by
`cblrs dashboard-users`), `cblrs dashboard` processes, and logging a page in.

The browser is Debian's chromium driven by Playwright (:mod:`cblrs.dashboard.browser`);
tests that need it are skipped, with the reason, when either is missing.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import yaml

from cblrs.cli.main import main
from cblrs.dashboard.browser import browser_problem, chromium_page
from cblrs.runtime.broker.mosquitto_config import (
    BrokerFiles,
    MosquittoProcess,
    find_mosquitto,
    free_port,
    write_broker_config,
)
from cblrs.site import load_site

REPO = Path(__file__).resolve().parents[2]
ADMIN = ("alice", "alice-admin-password")
VIEWER = ("bob", "bob-viewer-password")


def wait_until(predicate: Callable[[], object], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


@pytest.fixture
def page(tmp_path) -> Iterator:
    problem = browser_problem()
    if problem is not None:
        pytest.skip(problem)
    with chromium_page(profile=tmp_path / "chromium-profile") as page:
        yield page


class Broker:
    def __init__(self, files: BrokerFiles, process: MosquittoProcess):
        self.files, self.process = files, process

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.files.port}"

    def settings(self, user: str | None = None):
        return self.files.settings(user, connect_timeout_s=3.0, reconnect_min_s=0.05,
                                   reconnect_max_s=0.5)

    def password_file(self, user: str) -> Path:
        return self.files.password_files[user]


@pytest.fixture
def start_broker(tmp_path) -> Iterator[Callable[..., Broker]]:
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")
    started: list[Broker] = []

    def start(cameras=(), matchers=(), **options) -> Broker:
        # pytest's private temporary folders: as root the broker runs as root (never in
        # production; see broker-config's run_as).
        options.setdefault("run_as", "root" if os.geteuid() == 0 else None)
        # matchers: names (each serving plane 1), or name -> the planes it serves
        served = dict(matchers) if isinstance(matchers, dict) else list(matchers)
        files = write_broker_config(tmp_path / f"broker{len(started)}", list(cameras),
                                    served, port=free_port(), plane_ids=(1,), **options)
        process = MosquittoProcess.from_files(files)
        process.start()
        broker = Broker(files, process)
        started.append(broker)
        return broker

    yield start
    for broker in started:
        broker.process.stop()


@pytest.fixture(scope="module")
def wildtrack_site(wildtrack_root, tmp_path_factory) -> Path:
    """`cblrs site init` for WILDTRACK, with the places of sites/wildtrack.yaml."""
    path = tmp_path_factory.mktemp("site") / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(path)]) == 0
    document = yaml.safe_load(path.read_text())
    document["places"] = yaml.safe_load((REPO / "sites/wildtrack.yaml").read_text())["places"]
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def cblrs_command(*arguments: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", *arguments]


class Served(NamedTuple):
    """A running `cblrs dashboard`: its process, base URL and the URL it printed (with
    no --users: the login link of the run)."""

    process: subprocess.Popen
    url: str
    link: str


@pytest.fixture(scope="session")
def users_file(tmp_path_factory) -> Path:
    """A users file with an admin (:data:`ADMIN`) and a viewer (:data:`VIEWER`), written by
    `cblrs dashboard-users add` reading each password from standard input."""
    path = tmp_path_factory.mktemp("users") / "users.yaml"
    for (name, password), role in ((ADMIN, "admin"), (VIEWER, "viewer")):
        result = subprocess.run(
            cblrs_command("dashboard-users", "add", "--users", str(path), name, "--role", role,
                          "--password-stdin"),
            input=password + "\n", capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
    return path


def site_copy(site: Path, path: Path, change: Callable[[dict], object] | None = None) -> Path:
    """Write a copy of ``site`` to ``path`` (calibration paths made absolute, so that the copy
    finds them from its own folder), after ``change(document)`` if given."""
    document = yaml.safe_load(site.read_text())
    for camera in document["cameras"]:
        if "calibration" in camera:
            camera["calibration"]["file"] = str((site.parent
                                                 / camera["calibration"]["file"]).resolve())
    if change is not None:
        change(document)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def calibration_points(site_path: Path, camera: str = "CVLab1", count: int = 8) -> dict:
    """A save request for ``camera``: ground points it sees and their pixels (from the
    site's own calibration), as the calibration page would send them."""
    truth = load_site(site_path).camera(camera).camera
    grid = np.array([(x, y) for x in np.arange(-4.0, 10.0, 1.5)
                     for y in np.arange(-10.0, 28.0, 1.5)])
    pixels, valid = truth.world_to_pixel(grid)
    width, height = truth.image_size
    inside = valid & (pixels[:, 0] > 50) & (pixels[:, 0] < width - 50) \
        & (pixels[:, 1] > 50) & (pixels[:, 1] < height - 50)
    grid, pixels = grid[inside], pixels[inside]
    chosen = np.linspace(0, len(grid) - 1, count).astype(int)
    points = [{"u": float(u), "v": float(v), "x": float(x), "y": float(y), "name": f"p{i + 1}"}
              for i, ((u, v), (x, y)) in enumerate(zip(pixels[chosen], grid[chosen],
                                                      strict=True))]
    return {"camera": camera, "image_size": [int(width), int(height)], "points": points,
            "model": "auto", "unit": "metres"}


@pytest.fixture
def start_dashboard() -> Iterator[Callable[..., Served]]:
    """``start(*arguments)`` -> :class:`Served`: `cblrs dashboard --port 0 ...`, once serving."""
    processes: list[subprocess.Popen] = []

    def start(*arguments: str) -> Served:
        process = subprocess.Popen(cblrs_command("dashboard", "--port", "0", *arguments),
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        processes.append(process)
        line = process.stdout.readline() if process.stdout else ""
        if not line.startswith("dashboard on "):
            process.kill()
            _, error = process.communicate(timeout=10)
            raise AssertionError(f"the dashboard did not start: {line}{error}")
        link = line.split()[2]
        return Served(process, link.split("login?", 1)[0], link)

    yield start
    for process in processes:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


@pytest.fixture
def serve_app() -> Iterator[Callable[[object], str]]:
    """``serve(app)`` -> URL: an ASGI app served by uvicorn in a thread on a free loopback
    port (for tests that build the app themselves), stopped afterwards."""
    import uvicorn

    servers: list[tuple[object, threading.Thread, socket.socket]] = []

    def serve(app: object) -> str:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.bind(("127.0.0.1", 0))
        listener.listen(128)
        server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False,
                                               lifespan="off"))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]},
                                  daemon=True)
        thread.start()
        servers.append((server, thread, listener))
        wait_until(lambda: server.started, 30, "uvicorn to serve")
        return f"http://127.0.0.1:{listener.getsockname()[1]}/"

    yield serve
    for server, thread, listener in servers:
        server.should_exit = True  # type: ignore[attr-defined]
        thread.join(10)
        listener.close()


def login(page, url: str, user: tuple[str, str], path: str = "") -> None:
    """Log ``page`` in on the dashboard at ``url`` through its login form, then open
    ``path`` (the form sends the browser there)."""
    page.goto(f"{url}{path}")
    page.wait_for_url(lambda address: "/login" in address, timeout=60_000)
    page.fill("#user-name", user[0])
    page.fill("#password", user[1])
    # the page fixture skipped the test already when Playwright is missing
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    page.click("#login-button")
    try:
        # scrypt makes a login take a good part of a second, seconds on a loaded machine
        page.wait_for_url(lambda address: "/login" not in address, timeout=90_000)
    except PlaywrightTimeout:
        raise AssertionError(f"{user[0]} was not logged in: "
                             f"{page.inner_text('#login-message')!r}") from None
