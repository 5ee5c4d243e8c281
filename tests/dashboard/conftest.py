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
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import pytest
import yaml
from dashboard_helpers import ADMIN, REPO, VIEWER, cblrs_command, wait_until

from cblrs.cli.main import main
from cblrs.dashboard.browser import browser_problem, chromium_page
from cblrs.runtime.broker.mosquitto_config import (
    BrokerFiles,
    MosquittoProcess,
    find_mosquitto,
    free_port,
    write_broker_config,
)


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


