"""Running Mosquitto: :class:`MosquittoProcess` runs ``mosquitto -c mosquitto.conf`` as a child
process (tests, benchmarks, demos), waits until its port accepts connections and keeps its log;
:func:`find_mosquitto` and :func:`free_port` find the binary and a port.

The broker's configuration (users, ACL, TLS, persistence) is written by
:func:`cblrs.runtime.broker.mosquitto_config.write_broker_config`.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cblrs.errors import CblrsError
from cblrs.runtime.broker.credentials import append_private

if TYPE_CHECKING:
    from cblrs.runtime.broker.mosquitto_config import BrokerFiles

logger = logging.getLogger(__name__)

MOSQUITTO = "mosquitto"


class BrokerError(CblrsError):
    """The broker could not be configured or started."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that was free a moment ago (bind to port 0, read, release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def open_files_to_the_hard_limit() -> None:  # pragma: no cover - between fork and exec
    """Raise the process's soft limit of open files to its hard limit (a ``preexec_fn`` for
    the broker: Mosquitto keeps a connection that never sends its ``CONNECT`` for about 90 s
    and has no setting to shorten it, so its open-files limit is what silent connections
    must exhaust before a login fails; a shell's or systemd's soft limit, 1,024, is a few
    hundred connections a second away. nats-server, a Go program, raises its own)."""
    import resource

    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if hard == resource.RLIM_INFINITY or soft < hard:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    except (OSError, ValueError):
        pass


def find_mosquitto() -> str | None:
    """Path of the mosquitto binary, or None."""
    found = shutil.which(MOSQUITTO)
    if found:
        return found
    return "/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None


class MosquittoProcess:
    """``mosquitto -c CONFIG`` as a child process.

    Args:
        config_path: the configuration (e.g. from :func:`write_broker_config`).
        port: the port it listens on (to wait for).
        host: address to probe.
        startup_timeout_s: how long ``start()`` waits for the port.
        log_path: where its output goes (default: ``mosquitto.log`` beside the config).

    Use as a context manager; ``stop()`` sends SIGTERM so a persistent broker saves its
    database, ``restart()`` stops and starts it again on the same port.
    """

    def __init__(
        self,
        config_path: str | os.PathLike,
        port: int,
        *,
        host: str = "127.0.0.1",
        startup_timeout_s: float = 10.0,
        log_path: str | os.PathLike | None = None,
    ):
        self.config_path = Path(config_path)
        self.port = port
        self.host = host
        self.startup_timeout_s = startup_timeout_s
        self.log_path = Path(log_path) if log_path else self.config_path.with_name("mosquitto.log")
        self._process: subprocess.Popen | None = None

    @classmethod
    def from_files(cls, files: BrokerFiles, **options) -> MosquittoProcess:
        """The process for a configuration written by
        :func:`~cblrs.runtime.broker.mosquitto_config.write_broker_config`."""
        host = "127.0.0.1" if files.bind in ("0.0.0.0", "::") else files.bind
        return cls(files.config, files.port, host=host, **options)

    @property
    def running(self) -> bool:
        """Whether the broker process is alive."""
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        """The broker's process id (None before start)."""
        return None if self._process is None else self._process.pid

    def start(self) -> MosquittoProcess:
        """Start the broker and wait until its port accepts connections.

        Raises:
            BrokerError: no mosquitto binary, it exited, or the port stayed closed; the message
                ends with the last lines of its log.
        """
        if self.running:
            return self
        binary = find_mosquitto()
        if binary is None:
            raise BrokerError("mosquitto not found; install it (e.g. apt install mosquitto).")
        with append_private(self.log_path) as log:
            self._process = subprocess.Popen(
                [binary, "-c", str(self.config_path)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                preexec_fn=open_files_to_the_hard_limit if os.name == "posix" else None,
            )
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise BrokerError(
                    f"mosquitto exited with code {self._process.returncode}: {self.log_tail()}"
                )
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise BrokerError(
            f"mosquitto did not open {self.host}:{self.port} within "
            f"{self.startup_timeout_s:g} s: {self.log_tail()}"
        )

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM (mosquitto saves its persistence database), SIGKILL if it hangs."""
        process = self._process
        if process is None:
            return
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout_s)
        self._process = None

    def kill(self) -> None:
        """SIGKILL: a crash, without saving the persistence database."""
        process = self._process
        if process is not None and process.poll() is None:
            process.kill()
            process.wait(5)
        self._process = None

    def restart(self) -> None:
        """Stop the broker and start it again on the same port."""
        self.stop()
        self.start()

    def log_tail(self, lines: int = 15) -> str:
        """The last lines of the broker's log (for error messages)."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return "(no log)"
        return " | ".join(text.strip().splitlines()[-lines:]) or "(empty log)"

    def __enter__(self) -> MosquittoProcess:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()
