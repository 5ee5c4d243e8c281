"""Running a :class:`~cblrs.up.plan.SitePlan`: start the broker, the matchers, the dashboard and
the cameras as child processes, watch them, and stop them in order.

Every child runs in a process group of its own, so a Ctrl-C in the terminal reaches
``cblrs up`` alone and the stop keeps its order: the cameras first (each stops capturing and
waits for the matcher's confirmations of what it sent: what stays unconfirmed stays in its
spool), then the matchers (SIGTERM to the group: they finish, write their tracks and exit 0),
the dashboard and the broker (which saves its database). A child also gets SIGTERM when
``cblrs up`` itself dies (Linux's parent-death signal), so no process outlives it unseen.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cblrs.runtime.broker.mosquitto import open_files_to_the_hard_limit
from cblrs.up.plan import ProcessSpec, SitePlan, UpError, write_state

logger = logging.getLogger(__name__)

CAMERA_UNCONFIRMED = 3
"""``cblrs camera``'s exit code when some messages are still in its spool."""
STOP_GRACE_S = {"camera": 20.0, "matcher": 30.0, "dashboard": 5.0, "broker": 10.0}
"""How long each role may take to stop after SIGTERM before it is killed: a little more than
the watchdog of its own clean stop (cblrs.cli.stopping: 15 s for a camera, 25 s for a matcher)."""
CAMERA_START_S = 4.0
"""A fresh paced replay's first capture time lies this far after its cameras are started
(their start-up: imports, the reference, the broker connection)."""
READY_TIMEOUT_S = {"broker": 15.0, "matcher": 90.0, "dashboard": 60.0}
PREPARE_TIMEOUT_S = 90.0
"""NATS: how long the admin's ``cblrs matcher --prepare`` of a plane may take."""


def _child_setup() -> None:  # pragma: no cover - runs in the child between fork and exec
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: SIGTERM when cblrs up dies
    except (OSError, AttributeError):
        pass


def _broker_setup() -> None:  # pragma: no cover - runs in the child between fork and exec
    """The broker's: as :func:`_child_setup`, and its open-files limit raised to the hard
    one (silent connections must exhaust it: see
    :func:`cblrs.runtime.broker.mosquitto.open_files_to_the_hard_limit`)."""
    _child_setup()
    open_files_to_the_hard_limit()


@dataclass
class Child:
    """One started process and what is known about it."""

    spec: ProcessSpec
    log: Path
    process: subprocess.Popen | None = None
    state: str = "waiting"  # waiting, starting, running, finished, failed, stopped
    detail: str = ""
    returncode: int | None = None
    started_at: float | None = None
    stopping: bool = False  # cblrs up asked it to stop

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def last_error(self) -> str:
        """The line of its log that says what went wrong (its last line otherwise)."""
        try:
            lines = [line.strip() for line in
                     self.log.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            return "no log"
        errors = [line for line in lines if ": error: " in line or "Error" in line]
        return (errors or lines or ["no output"])[-1]


@dataclass
class SiteRunner:
    """Starts, watches and stops the processes of a plan.

    Args:
        plan: the site's plan (prepared: broker configuration and references written).
        mosquitto: the broker binary (Mosquitto's, or nats-server's on the NATS backbone).
        until_done: the matchers stop once every camera said its final "offline" and all is
            tracked; :meth:`watch` returns when every camera and matcher has ended.
        report: called with a status line or table whenever something changes.
        status_interval_s: at most this often a new status is reported.
    """

    plan: SitePlan
    mosquitto: str
    until_done: bool = False
    report: Callable[[str], None] = print
    status_interval_s: float = 2.0
    children: list[Child] = field(default_factory=list)
    dashboard_url: str | None = None
    failure: str | None = None
    started_at: float = field(default_factory=time.monotonic)
    first_track_s: float | None = None
    _last_status: str = ""

    def __post_init__(self) -> None:
        self.children = [Child(spec, self.plan.logs_dir / f"{spec.name}.log")
                         for spec in self.plan.processes(self.until_done, self.mosquitto)]

    # ------------------------------------------------------------------ start
    def child(self, name: str) -> Child:
        return next(child for child in self.children if child.spec.name == name)

    def of_role(self, role: str) -> list[Child]:
        return [child for child in self.children if child.spec.role == role]

    def _spawn(self, child: Child) -> None:
        environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with _private_log(child.log) as log:
            log.write(f"---- {time.strftime('%Y-%m-%dT%H:%M:%S')} cblrs up starts: "
                      f"{' '.join(child.spec.argv)}\n".encode())
            log.flush()
            child.process = subprocess.Popen(
                child.spec.argv, stdout=log, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL, env=environment, start_new_session=True,
                preexec_fn=(None if not sys.platform.startswith("linux")
                            else _broker_setup if child.spec.role == "broker"
                            else _child_setup),
            )
        child.state = "starting"
        child.started_at = time.monotonic()

    def _wait_ready(self, child: Child, ready: Callable[[], bool], stop: threading.Event
                    ) -> bool:
        deadline = time.monotonic() + READY_TIMEOUT_S[child.spec.role]
        while not ready():
            if stop.is_set():
                return False
            if not child.alive:
                child.returncode = child.process.returncode if child.process else None
                child.state = "failed"
                raise UpError(f"{child.spec.name} exited with code {child.returncode} while "
                              f"starting: {child.last_error()} (log: {child.log}).")
            if time.monotonic() > deadline:
                raise UpError(f"{child.spec.name} was not ready within "
                              f"{READY_TIMEOUT_S[child.spec.role]:g} s (log: {child.log}).")
            time.sleep(0.1)
        child.state = "running"
        return True

    def start(self, stop: threading.Event | None = None) -> bool:
        """Start every process in order, each once the ones before it are ready; False when
        ``stop`` was set meanwhile (what started is left for :meth:`stop`).

        Raises:
            UpError: a process failed or was not ready in time (everything started so far
                is stopped).
        """
        stop = stop or threading.Event()
        try:
            broker = self.child("broker")
            self._spawn(broker)
            ports = [self.plan.broker_port, *([self.plan.mqtt_port] if self.plan.mqtt_port
                                              else [])]
            if not self._wait_ready(broker, lambda: all(map(_accepts, ports)), stop):
                return False
            broker.detail = self.plan.backbone_url
            for spec in self.plan.prepare_specs():
                if stop.is_set():
                    return False
                self._run_to_end(spec)
            matchers = self.of_role("matcher")
            for matcher in matchers:
                self._spawn(matcher)
            for matcher, plane in zip(matchers, self.plan.planes, strict=True):
                user = self.plan.matcher_user(plane)
                if not self._wait_ready(matcher, lambda user=user, matcher=matcher: _log_has(
                        matcher, f"matcher {user}: plane"), stop):
                    return False
            # The cameras' replay starts now (a restart keeps its saved epoch).
            if self.plan.fresh_epoch:
                self.plan.epoch = float(int(time.time() + CAMERA_START_S))
                self.plan.fresh_epoch = False
                write_state(self.plan)
                for camera in self.of_role("camera"):
                    name = camera.spec.name.removeprefix("camera-")
                    run = next(item for item in self.plan.cameras if item.name == name)
                    camera.spec = self.plan.camera_spec(run)
            # The dashboard and the cameras start together: neither waits for the other.
            dashboards = self.of_role("dashboard")
            for child in [*dashboards, *self.of_role("camera")]:
                if stop.is_set():
                    return False
                self._spawn(child)
                if child.spec.role == "camera":
                    child.state = "running"
            for dashboard in dashboards:
                if not self._wait_ready(dashboard, lambda d=dashboard: self._read_url(d), stop):
                    return False
            return True
        except BaseException:
            self.stop()
            raise

    def _run_to_end(self, spec: ProcessSpec) -> None:
        """Run a one-off step (NATS: a plane's preparation) to its end, logged like a child.

        Raises:
            UpError: it failed or took longer than :data:`PREPARE_TIMEOUT_S`.
        """
        child = Child(spec, self.plan.logs_dir / f"{spec.name}.log")
        self._spawn(child)
        assert child.process is not None
        try:
            code = child.process.wait(PREPARE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            _signal_group(child, signal.SIGKILL)
            child.process.wait(5)
            raise UpError(f"{spec.name} did not end within {PREPARE_TIMEOUT_S:g} s (log: "
                          f"{child.log}).") from None
        if code != 0:
            raise UpError(f"{spec.name} exited with code {code}: {child.last_error()} (log: "
                          f"{child.log}).")

    def _read_url(self, dashboard: Child) -> bool:
        for line in _log_lines(dashboard):
            if line.startswith("{") and '"url"' in line:
                try:
                    self.dashboard_url = json.loads(line)["url"]
                except (ValueError, KeyError):
                    continue
                dashboard.detail = self.dashboard_url.split("login?")[0]
                return True
        return False

    # ------------------------------------------------------------------ watch
    def poll(self) -> None:
        """Update every child's state from its process and the matchers' databases."""
        for child in self.children:
            if child.process is None or child.state in ("finished", "failed", "stopped"):
                continue
            code = child.process.poll()
            if code is None:
                continue
            child.returncode = code
            role = child.spec.role
            if role == "camera" and code == CAMERA_UNCONFIRMED:
                child.detail = "some messages unconfirmed: kept in its spool"
            if child.stopping:
                clean = code in (0, -signal.SIGTERM) or (role == "camera"
                                                         and code == CAMERA_UNCONFIRMED)
                child.state = "stopped" if clean else "failed"
            elif role == "camera" and code == 0:
                child.state = "finished"
            elif role == "camera" and code == CAMERA_UNCONFIRMED:
                child.state = "finished"
            elif role == "matcher" and code == 0 and self.until_done:
                child.state = "finished"
            else:
                child.state = "failed"
                if self.failure is None:
                    self.failure = (f"{child.spec.name} exited with code {code}: "
                                    f"{child.last_error()} (log: {child.log})")
        stored: dict[str, int] = {}
        for matcher, plane in zip(self.of_role("matcher"), self.plan.planes, strict=True):
            counts = database_counts(self.plan.database(plane), self.webhooks)
            stored.update(counts["stored"])
            if counts["counters"]:
                numbers = counts["counters"]
                matcher.detail = (f"received {numbers.get('received', 0)}, processed "
                                  f"{numbers.get('processed', 0)}, tracks "
                                  f"{counts['track_ids']} ({counts['track_rows']} rows)"
                                  + places_detail(counts["places"], len(self.plan.site.places))
                                  + alerts_detail(counts.get("alerts")))
                if counts["track_rows"] and self.first_track_s is None:
                    self.first_track_s = time.monotonic() - self.started_at
        for camera in self.of_role("camera"):
            name = camera.spec.name.removeprefix("camera-")
            text = f"stored {stored.get(name, 0)}"
            if camera.detail and "spool" in camera.detail:
                text += "; " + camera.detail.split("; ")[-1]
            camera.detail = text

    def status_table(self) -> str:
        rows = [(child.spec.name, child.state + (f" ({child.returncode})"
                                                 if child.state == "failed" else ""),
                 str(child.process.pid) if child.process is not None else "-", child.detail)
                for child in self.children]
        widths = [max(len(row[index]) for row in [("process", "state", "pid", ""), *rows])
                  for index in range(3)]
        lines = [f"{'process':<{widths[0]}}  {'state':<{widths[1]}}  {'pid':>{widths[2]}}  "
                 "detail"]
        lines += [f"{name:<{widths[0]}}  {state:<{widths[1]}}  {pid:>{widths[2]}}  {detail}"
                  for name, state, pid, detail in rows]
        return "\n".join(lines)

    def done(self) -> bool:
        """Whether a run with ``until_done`` has ended: every camera and matcher finished."""
        return self.until_done and all(
            child.state in ("finished", "failed")
            for child in self.children if child.spec.role in ("camera", "matcher"))

    def watch(self, stop: threading.Event) -> None:
        """Report the status on change until ``stop`` is set, a process fails, or (until
        done) every camera and matcher has finished."""
        last_report = 0.0
        while True:
            self.poll()
            table = self.status_table()
            now = time.monotonic()
            if table != self._last_status and now - last_report >= self.status_interval_s:
                self._last_status, last_report = table, now
                self.report(table)
            if self.failure is not None or self.done() or stop.is_set():
                return
            stop.wait(0.25)

    # ------------------------------------------------------------------ stop
    def stop(self) -> None:
        """Stop in order: cameras, matchers, dashboard, broker (SIGTERM, then SIGKILL after
        the role's grace)."""
        for role in ("camera", "matcher", "dashboard", "broker"):
            children = [child for child in self.of_role(role) if child.alive]
            for child in children:
                child.stopping = True
                _signal_group(child, signal.SIGTERM)
            deadline = time.monotonic() + STOP_GRACE_S[role]
            for child in children:
                assert child.process is not None
                try:
                    child.process.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    logger.warning("%s did not stop within %g s: killed", child.spec.name,
                                   STOP_GRACE_S[role])
                    _signal_group(child, signal.SIGKILL)
                    child.process.wait(5)
                    child.state = "failed"
                    child.detail = "killed"
                    if self.failure is None:
                        self.failure = (f"{child.spec.name} did not stop within "
                                        f"{STOP_GRACE_S[role]:g} s and was killed "
                                        f"(log: {child.log})")
            self.poll()
        for child in self.children:
            if child.process is not None and child.state in ("starting", "running"):
                child.state = "stopped"

    def kill(self) -> None:
        """SIGKILL every process group at once (a second Ctrl-C)."""
        for child in self.children:
            if child.alive:
                _signal_group(child, signal.SIGKILL)

    # ------------------------------------------------------------------ results
    def summary(self) -> dict[str, Any]:
        planes = {}
        for plane in self.plan.planes:
            counts = database_counts(self.plan.database(plane), self.webhooks)
            tracks = self.plan.tracks_file(plane)
            planes[str(plane)] = {
                "database": str(self.plan.database(plane)),
                "stored": counts["stored"], "counters": counts["counters"],
                "pending": counts["pending"], "track_ids": counts["track_ids"],
                "track_rows": counts["track_rows"],
                "tracks_file": str(tracks) if tracks.is_file() else None,
            }
            if len(self.plan.site.places):
                planes[str(plane)]["counts"] = plane_counts(self.plan.site.places,
                                                            counts["places"], plane)
            if "alerts" in counts:
                planes[str(plane)]["alerts"] = counts["alerts"]
        return {
            "site": str(self.plan.site_path), "out": str(self.plan.out),
            "backbone": self.plan.backbone, "broker": self.plan.backbone_url,
            "dashboard": self.dashboard_url,
            "processes": {child.spec.name: {"state": child.state,
                                            "exit_code": child.returncode,
                                            "log": str(child.log)}
                          for child in self.children},
            "planes": planes, "failure": self.failure,
            "first_track_s": self.first_track_s,
            "elapsed_s": time.monotonic() - self.started_at,
        }

    @property
    def webhooks(self) -> tuple[str, ...] | None:
        """The site's webhooks (None: the site has no alert rules)."""
        alerts = self.plan.site.alerts
        return tuple(hook.name for hook in alerts.webhooks) if alerts.rules else None

    def webhook_failure(self, plane: int, webhook: str) -> str | None:
        """The matcher's last sentence on why ``webhook`` got no alert, from its log."""
        matcher = self.of_role("matcher")[self.plan.planes.index(plane)]
        lines = [line for line in _log_lines(matcher) if f"webhook {webhook}: " in line
                 and "not delivered" in line]
        return lines[-1].split(f"webhook {webhook}: ", 1)[1].strip() if lines else None

    def unconfirmed_cameras(self) -> list[str]:
        """The cameras that ended with messages still in their spools (sent at their next
        start)."""
        return [child.spec.name.removeprefix("camera-") for child in self.of_role("camera")
                if child.returncode == CAMERA_UNCONFIRMED]

    def exit_code(self, stopped: bool = False) -> int:
        """0 when every process ended well; 1 when a process failed; 3 when a camera whose
        source ended still holds messages in its spool. A camera stopped by a signal keeps
        what the matcher has not yet confirmed in its spool by design (0, not 3)."""
        if self.failure is not None or any(child.state == "failed" for child in self.children):
            return 1
        if self.unconfirmed_cameras() and not stopped:
            return CAMERA_UNCONFIRMED
        return 0


def _private_log(path: Path) -> Any:
    """Open a child's log for appending, readable by this user only (folder 0700, file
    0600, also when an older run left them open to others): the dashboard's log holds its
    admin login link, and the others name cameras and logins."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    if path.parent.stat().st_uid == os.getuid():
        os.chmod(path.parent, 0o700)
    handle = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.fchmod(handle, 0o600)
    return os.fdopen(handle, "ab")


def _signal_group(child: Child, signum: int) -> None:
    if child.process is None:
        return
    try:
        os.killpg(child.process.pid, signum)
    except (ProcessLookupError, PermissionError):
        pass


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def _log_lines(child: Child) -> list[str]:
    try:
        return child.log.read_text(errors="replace").split("cblrs up starts:")[-1].splitlines()
    except OSError:
        return []


def _log_has(child: Child, text: str) -> bool:
    return any(text in line for line in _log_lines(child))


def places_detail(places: dict[str, Any], count: int) -> str:
    """The status table's words on a plane's counts (none when the site has no places):
    the lines' crossings and the zones' entries so far."""
    if not count:
        return ""
    crossings = sum(sum(row.values()) for row in places["lines"].values())
    entries = sum(row["entries"] for row in places["zones"].values())
    return f"; counted {crossings} crossings, {entries} zone entries"


def counts_text(places: dict[str, Any]) -> str:
    """A plane's counts in one line: ``line +positive/-negative`` and ``zone in/out``."""
    lines = [f"{name} +{row['positive']}/-{row['negative']}"
             for name, row in places["lines"].items()]
    zones = [f"{name} {row['entries']} in/{row['exits']} out"
             for name, row in places["zones"].items()]
    return "; ".join(part for part in (", ".join(lines), ", ".join(zones)) if part) or "none yet"


def alerts_detail(alerts: dict[str, Any] | None) -> str:
    """The status table's words on a plane's alerts: how many fired, the episodes firing
    now, and the alerts a webhook or the broker has not yet acknowledged."""
    if alerts is None:
        return ""
    text = f"; alerts {alerts['fired']} fired"
    if alerts["firing"]:
        text += f", firing {', '.join(alerts['firing'])}"
    waiting = [f"{name} {count}" for name, count in alerts["undelivered"].items() if count]
    if waiting:
        text += f"; not yet delivered: {', '.join(waiting)}"
    return text


def _alert_counts(connection: sqlite3.Connection, webhooks: tuple[str, ...]) -> dict[str, Any]:
    from cblrs.runtime.outputs.alert_service import BACKBONE  # the broker's outbox name

    fired, cleared = connection.execute(
        "SELECT COUNT(*) FILTER (WHERE state = 'fired'), COUNT(*) FILTER (WHERE state = "
        "'cleared') FROM alerts").fetchone()
    firing = [episode for (episode,) in connection.execute(
        "SELECT episode FROM alerts WHERE state = 'fired' AND episode NOT IN (SELECT episode "
        "FROM alerts WHERE state = 'cleared') ORDER BY id")]
    undelivered = {}
    for name, key in (("broker", BACKBONE), *((hook, hook) for hook in webhooks)):
        undelivered[name] = int(connection.execute(
            "SELECT COUNT(*) FROM alerts WHERE NOT EXISTS (SELECT 1 FROM "
            "json_each(alerts.delivered) WHERE json_each.value = ?)", (key,)).fetchone()[0])
    return {"fired": int(fired), "cleared": int(cleared), "firing": firing,
            "undelivered": undelivered}


PLACE_MEASURES = {"lines": ("positive", "negative"), "zones": ("entries", "exits")}
"""What ``cblrs up`` reports of the analytics' counters: a line's crossings per direction, a
zone's entries and exits (every class together)."""


def plane_counts(places: Any, counted: dict[str, Any], plane: int) -> dict[str, Any]:
    """``counted`` (:func:`_place_counts`) with every place of ``plane`` (a
    :class:`~cblrs.places.Places`' places on it or on every plane), 0 where nothing was
    counted yet, in the site file's order."""
    result: dict[str, Any] = {}
    for kind, items in (("lines", places.lines), ("zones", places.zones)):
        zero = dict.fromkeys(PLACE_MEASURES[kind], 0)
        result[kind] = {item.name: counted[kind].get(item.name, dict(zero)) for item in items
                        if item.plane_id in (None, plane)}
    return result


def _place_counts(connection: sqlite3.Connection) -> dict[str, dict[str, dict[str, int]]]:
    """The analytics' counters so far: ``{"lines": {line: {"positive": n, "negative": n}},
    "zones": {zone: {"entries": n, "exits": n}}}`` (the places counted at least once)."""
    places: dict[str, dict[str, dict[str, int]]] = {kind: {} for kind in PLACE_MEASURES}
    for place, measure, value in connection.execute(
            "SELECT place, measure, SUM(value) FROM counts GROUP BY place, measure "
            "ORDER BY place, measure"):
        for kind, measures in PLACE_MEASURES.items():
            if measure in measures:
                row = places[kind].setdefault(place, dict.fromkeys(measures, 0))
                row[measure] = int(value)
    return places


def database_counts(path: Path, webhooks: tuple[str, ...] | None = None) -> dict[str, Any]:
    """What a matcher's database holds now: messages stored per camera, pending ones, its
    counters and tracks, what its analytics counted per place (``places``: see
    :func:`_place_counts`) (zeros while it does not exist; read-only, never blocks a writer);
    with ``webhooks`` (the site has alert rules), its alerts too: how many fired and cleared,
    the episodes firing now, and per webhook (and ``broker``) the alerts not yet delivered."""
    counts: dict[str, Any] = {"stored": {}, "pending": 0, "counters": {}, "track_ids": 0,
                              "track_rows": 0, "places": {"lines": {}, "zones": {}}}
    if webhooks is not None:
        counts["alerts"] = {"fired": 0, "cleared": 0, "firing": [],
                            "undelivered": dict.fromkeys(("broker", *webhooks), 0)}
    if not path.is_file():
        return counts
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.5)
        try:
            for camera, count in connection.execute(
                    "SELECT camera_id, COUNT(*) FROM inbox GROUP BY camera_id"):
                counts["stored"][camera] = int(count)
            counts["pending"] = int(connection.execute(
                "SELECT COUNT(*) FROM inbox WHERE status = 'pending'").fetchone()[0])
            counts["counters"] = {name: int(value) for name, value in
                                  connection.execute("SELECT name, value FROM counters")}
            rows, ids = connection.execute(
                "SELECT COUNT(*), COUNT(DISTINCT track_id) FROM tracks").fetchone()
            counts["track_rows"], counts["track_ids"] = int(rows), int(ids)
            if webhooks is not None and connection.execute(
                    "SELECT 1 FROM sqlite_master WHERE name = 'alerts'").fetchone():
                counts["alerts"] = _alert_counts(connection, webhooks)
            if connection.execute(
                    "SELECT 1 FROM sqlite_master WHERE name = 'counts'").fetchone():
                counts["places"] = _place_counts(connection)
        finally:
            connection.close()
    except sqlite3.Error:
        pass  # being created, or busy: the next look sees it
    return counts
