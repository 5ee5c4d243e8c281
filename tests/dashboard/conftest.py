"""Fixtures for the dashboard tests: a headless Chromium page, Mosquitto brokers with users,
the WILDTRACK site, and `cblrs dashboard` processes.

The browser is Debian's chromium driven by Playwright (:mod:`cblrs.dashboard.browser`);
tests that need it are skipped, with the reason, when either is missing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from cblrs.cli.main import main
from cblrs.dashboard.browser import browser_problem, chromium_page
from cblrs.runtime.broker import (
    BrokerFiles,
    MosquittoProcess,
    find_mosquitto,
    free_port,
    write_broker_config,
)

REPO = Path(__file__).resolve().parents[2]


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
        files = write_broker_config(tmp_path / f"broker{len(started)}", list(cameras),
                                    list(matchers), port=free_port(), plane_ids=(1,), **options)
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


@pytest.fixture
def start_dashboard() -> Iterator[Callable[..., tuple[subprocess.Popen, str]]]:
    """``start(*arguments)`` -> (process, URL): `cblrs dashboard --port 0 ...`, once serving."""
    processes: list[subprocess.Popen] = []

    def start(*arguments: str) -> tuple[subprocess.Popen, str]:
        process = subprocess.Popen(cblrs_command("dashboard", "--port", "0", *arguments),
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        processes.append(process)
        line = process.stdout.readline() if process.stdout else ""
        if not line.startswith("dashboard on "):
            process.kill()
            _, error = process.communicate(timeout=10)
            raise AssertionError(f"the dashboard did not start: {line}{error}")
        return process, line.split()[2]

    yield start
    for process in processes:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
