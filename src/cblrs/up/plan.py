"""What ``cblrs up`` runs for a site file: the broker's configuration, the references and one
command line per process (broker, a matcher per plane, the dashboard, a camera per camera).

A :class:`SitePlan` is pure description: the same plan starts the processes
(:mod:`cblrs.up.runner`) and writes systemd units and a container definition
(:mod:`cblrs.up.units`). Its state folder holds everything a run writes::

    <out>/up.json              the run's identity: site, users, broker port, replay epoch
    <out>/broker/              mosquitto.conf, hashed passwords, ACL, persistence (or, on
                               NATS, n1/n1.conf with the users' hashes and JetStream's store)
    <out>/clients/<user>/      each login's password file (0600)
    <out>/references/          the cameras' reference PNGs (rendered when missing)
    <out>/plane<P>.db          the matcher's SQLite file of plane P
    <out>/tracks-plane<P>.txt  its tracks (AI City format), written when it stops
    <out>/spool/<camera>.db    each camera's spool
    <out>/logs/<process>.log   each process's output

A restarted ``cblrs up`` on the same folder keeps the epoch, the logins and the spools, so a
replay stopped half-way resumes: what its cameras sent before is recognised as duplicates and
what they still held is sent.
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError
from cblrs.runtime.broker.mosquitto import free_port
from cblrs.site import Site, load_site
from cblrs.site.schema import SourceModel
from cblrs.up.backbone import ADMIN, DEFAULT_NATS_PORT, MQTT, NATS
from cblrs.up.host import port_is_free

STATE_FILE = "up.json"
DEFAULT_BROKER_PORT = 1883
DEFAULT_DASHBOARD_PORT = 8080
START_MARGIN_S = 6.0
"""A paced replay's first capture time lies this far after ``cblrs up`` starts its cameras
(their start-up: imports, the reference, the broker connection)."""
FAST_EPOCH_AGO_S = 300.0
"""An unpaced replay's capture times start this long before now (none lies in the future)."""


class UpError(CblrsError):
    """The site cannot be started as asked (one sentence)."""


@dataclass(frozen=True)
class CameraRun:
    """One camera ``cblrs up`` runs: its name, the plane it publishes to, its source and the
    frames per second it sends (None: not known)."""

    name: str
    plane: int
    source: SourceModel
    fps: float | None = None


@dataclass(frozen=True)
class ProcessSpec:
    """One process of the site.

    Attributes:
        name: ``broker``, ``matcher-<plane>``, ``dashboard`` or ``camera-<name>``.
        role: broker, matcher, dashboard or camera.
        argv: its whole command line (the ``cblrs`` ones run this interpreter's cblrs).
        after: the processes that must run before it starts.
    """

    name: str
    role: str
    argv: list[str]
    after: tuple[str, ...] = ()


def cblrs_command() -> list[str]:
    """How this cblrs is started as a child process: this interpreter, ``-m cblrs.cli.main``."""
    return [sys.executable, "-m", "cblrs.cli.main"]


def safe_stem(name: str) -> str:
    """A file stem for a camera name (the name ``cblrs render`` gives its reference)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "camera"




@dataclass
class SitePlan:
    """Everything ``cblrs up`` needs for one site file (see the module docstring).

    Attributes:
        site: the loaded site.
        site_path: the site file, resolved.
        out: the state folder, resolved.
        cameras: the cameras to run, in the site's order.
        planes: plane ids, each with one matcher.
        broker_port: the broker's listener port.
        dashboard_port: the dashboard's port (0: a free one).
        epoch: seconds since 1970 added to every replay's recorded timestamps.
        realtime: pace replays by their timestamps (False: as fast as possible).
        speed: the pace's speed-up.
        run_as: the user Mosquitto runs as when started as root.
        dashboard: run the dashboard.
        backbone: ``mqtt`` (Mosquitto) or ``nats`` (a NATS server with JetStream; see
            :mod:`cblrs.up.backbone`).
        mqtt_port: NATS only: the server's MQTT listener (the same logins; for MQTT
            clients such as cameras that speak MQTT only).
        monitor_port: NATS only: the server's monitoring port (loopback).
        fresh_epoch: the epoch is not a saved run's: the runner sets it when it starts the
            cameras (a paced replay then begins as they start).
        made_at: when the plan was made (seconds since 1970): this run's start. With
            ``until_done``, only the cameras' ends after it count (not an earlier run's).
    """

    site: Site
    site_path: Path
    out: Path
    cameras: list[CameraRun]
    planes: list[int]
    broker_port: int
    dashboard_port: int
    epoch: float
    realtime: bool = True
    speed: float = 1.0
    run_as: str | None = None
    dashboard: bool = True
    fresh_epoch: bool = False
    backbone: str = MQTT
    mqtt_port: int | None = None
    monitor_port: int | None = None
    command: list[str] = field(default_factory=cblrs_command)
    made_at: float = field(default_factory=time.time)

    # ------------------------------------------------------------------ paths
    @property
    def broker_dir(self) -> Path:
        return self.out / "broker"

    @property
    def clients_dir(self) -> Path:
        return self.out / "clients"

    @property
    def references_dir(self) -> Path:
        return self.out / "references"

    @property
    def logs_dir(self) -> Path:
        return self.out / "logs"

    def database(self, plane: int) -> Path:
        return self.out / f"plane{plane}.db"

    def tracks_file(self, plane: int) -> Path:
        return self.out / f"tracks-plane{plane}.txt"

    def spool(self, camera: str) -> Path:
        return self.out / "spool" / f"{safe_stem(camera)}.db"

    def reference(self, camera: str) -> Path:
        return self.references_dir / f"{safe_stem(camera)}.png"

    def password_file(self, user: str) -> Path:
        return self.clients_dir / user / f"{user}.password"

    @staticmethod
    def matcher_user(plane: int) -> str:
        return f"matcher{plane}"

    @property
    def broker_address(self) -> str:
        return f"127.0.0.1:{self.broker_port}"

    @property
    def backbone_url(self) -> str:
        """What the clients connect to: ``nats://127.0.0.1:PORT`` or ``127.0.0.1:PORT``."""
        return (f"nats://{self.broker_address}" if self.backbone == NATS
                else self.broker_address)

    @property
    def broker_config(self) -> Path:
        """The broker's configuration file (Mosquitto's, or the NATS node's)."""
        return (self.broker_dir / "n1" / "n1.conf" if self.backbone == NATS
                else self.broker_dir / "mosquitto.conf")

    @property
    def users(self) -> list[str]:
        """Every login of the run (the NATS admin too)."""
        return [*(camera.name for camera in self.cameras),
                *(self.matcher_user(plane) for plane in self.planes), "viewer",
                *([ADMIN] if self.backbone == NATS else [])]

    # ------------------------------------------------------------------ command lines
    def login(self, user: str) -> list[str]:
        """A client's backbone and login options (cameras and matchers)."""
        where = (["--backbone", self.backbone_url] if self.backbone == NATS
                 else ["--broker", self.broker_address])
        return [*where, "--username", user, "--password-file", str(self.password_file(user))]

    def dashboard_login(self) -> list[str]:
        """The dashboard's: the viewer's login on the site's backbone (MQTT or NATS)."""
        return self.login("viewer")

    def broker_spec(self, binary: str = "mosquitto") -> ProcessSpec:
        return ProcessSpec("broker", "broker", [binary, "-c", str(self.broker_config)])

    def prepare_specs(self) -> list[ProcessSpec]:
        """NATS only: the admin's ``cblrs matcher --prepare`` of each plane (its streams,
        consumer and the lease bucket, which runtime logins may not create), run to its end
        before the matchers start."""
        if self.backbone != NATS:
            return []
        return [ProcessSpec(
            f"prepare-{plane}", "prepare",
            [*self.command, "matcher", "--prepare", "--site", str(self.site_path), "--plane",
             str(plane), "--db", str(self.database(plane)), "--client-id",
             self.matcher_user(plane), *self.login(ADMIN)], ("broker",))
            for plane in self.planes]

    def camera_fps(self, plane: int) -> float | None:
        """The frame rate the matcher of ``plane`` is told (``--camera-fps``): its fastest
        camera's; None when a camera of the plane has none (a rate set too low would make a
        faster camera's frames late, so an unknown one is not guessed)."""
        rates = [camera.fps for camera in self.cameras if camera.plane == plane]
        if not rates or any(rate is None for rate in rates):
            return None
        return max(rate for rate in rates if rate is not None)

    def matcher_spec(self, plane: int, until_done: bool = False) -> ProcessSpec:
        argv = [*self.command, "matcher", "--site", str(self.site_path), "--plane", str(plane),
                "--db", str(self.database(plane)), "--out-tracks", str(self.tracks_file(plane)),
                *self.login(self.matcher_user(plane))]
        fps = self.camera_fps(plane)
        if fps is not None:
            argv += ["--camera-fps", repr(fps)]
        if until_done:  # the ends of an earlier run's replays (retained) are not this run's
            argv += ["--until-cameras-offline", "--offline-after", repr(self.made_at)]
        return ProcessSpec(f"matcher-{plane}", "matcher", argv, ("broker",))

    def dashboard_spec(self) -> ProcessSpec:
        plane = self.planes[0]
        argv = [*self.command, "dashboard", "--site", str(self.site_path), "--plane", str(plane),
                "--db", str(self.database(plane)), "--port", str(self.dashboard_port), "--json",
                *self.dashboard_login()]
        return ProcessSpec("dashboard", "dashboard", argv,
                           ("broker", *(f"matcher-{p}" for p in self.planes)))

    def camera_spec(self, camera: CameraRun) -> ProcessSpec:
        argv = [*self.command, "camera", "--camera", camera.name, "--plane", str(camera.plane),
                "--reference", str(self.reference(camera.name)),
                "--spool", str(self.spool(camera.name)), "--json",
                *source_options(camera.source, self.site.folder)]
        if camera.source.kind != "url":
            argv += ["--epoch", repr(self.epoch)]
            if self.realtime and camera.source.realtime:
                argv += ["--realtime", "--speed", repr(self.speed)]
        argv += self.login(camera.name)
        return ProcessSpec(f"camera-{camera.name}", "camera", argv,
                           ("broker", f"matcher-{camera.plane}"))

    def processes(self, until_done: bool = False, mosquitto: str = "mosquitto"
                  ) -> list[ProcessSpec]:
        """Every process in start order: broker, matchers, dashboard, cameras."""
        specs = [self.broker_spec(mosquitto)]
        specs += [self.matcher_spec(plane, until_done) for plane in self.planes]
        if self.dashboard:
            specs.append(self.dashboard_spec())
        specs += [self.camera_spec(camera) for camera in self.cameras]
        return specs

    def files_read(self) -> list[Path]:
        """The files and folders outside the state folder the processes read (the site file,
        its sources, models and calibrations), resolved."""
        paths = {self.site_path}
        for camera in self.cameras:
            source = camera.source
            if source.path:
                paths.add((self.site.folder / source.path).resolve())
            detector = source.detector
            for name in ("model", "weights"):
                value = getattr(detector, name, None) if detector is not None else None
                if value:
                    paths.add((self.site.folder / value).resolve())
        for spec in self.site.model.cameras:
            if spec.calibration is not None:
                paths.add((self.site.folder / spec.calibration.file).resolve())
            if spec.points_file is not None:
                paths.add((self.site.folder / spec.points_file).resolve())
        if self.site.model.map is not None and self.site.model.map.image:
            paths.add((self.site.folder / self.site.model.map.image).resolve())
        return sorted(paths)


def source_options(source: SourceModel, folder: Path) -> list[str]:
    """The ``cblrs camera`` options of a site file's ``source:`` (paths made absolute)."""

    def path(value: str) -> str:
        return str((folder / value).resolve())

    options: list[str]
    if source.kind == "dataset":
        options = ["--dataset", path(source.path or "")]
    elif source.kind == "detections":
        options = ["--detections", path(source.path or ""), "--format", source.format]
    elif source.kind == "images":
        options = ["--images", path(source.path or "")]
    elif source.kind == "video":
        options = ["--video", path(source.path or "")]
    else:
        options = ["--video", source.url or "", "--live"]
    if source.frames is not None:
        options += ["--frames", source.frames]
    if source.fps is not None:
        options += ["--fps", repr(source.fps)]
    detector = source.detector
    if detector is not None:
        options += ["--detector", detector.kind]
        if detector.model:
            options += ["--model", path(detector.model)]
        if detector.weights:
            options += ["--weights", path(detector.weights)]
        if detector.confidence is not None:
            options += ["--confidence", repr(detector.confidence)]
        if detector.colour is not None:
            options += ["--blob-colour", ",".join(str(int(value)) for value in detector.colour)]
    return options


def default_out(site_path: Path) -> Path:
    """The default state folder: ``cblrs-<site file stem>`` in the current folder."""
    return Path.cwd() / f"cblrs-{safe_stem(site_path.stem)}"


def make_plan(
    site_path: str | Path,
    out: str | Path | None = None,
    *,
    broker_port: int | None = None,
    dashboard_port: int = DEFAULT_DASHBOARD_PORT,
    realtime: bool = True,
    speed: float | None = None,
    run_as: str | None = None,
    dashboard: bool = True,
    check_files: bool = True,
    backbone: str = MQTT,
) -> SitePlan:
    """The plan of a site file: validated, with its state folder's saved run reused.

    Args:
        site_path: the site file; every camera needs a ``source:``.
        out: the state folder (default :func:`default_out`).
        broker_port: the broker's port (None: the saved one, else 1883 when free, else a free
            one; 0: a free one).
        dashboard_port: the dashboard's port (0: a free one).
        realtime: pace replays by their timestamps (a source may opt out with
            ``realtime: false``); False replays as fast as possible.
        speed: speed-up of paced replays (None: the saved run's, else 1); a restart goes on
            with its run's pace, so another speed on a state folder is refused.
        run_as: the user Mosquitto runs as when started as root.
        dashboard: plan the dashboard too.
        check_files: refuse a source whose file does not exist.
        backbone: ``mqtt`` or ``nats`` (:func:`cblrs.up.backbone.choose_backbone` picks it);
            a state folder keeps the backbone it was made with.

    Raises:
        UpError: a camera without a source or plane, a missing file, a bad option.
        SiteError: the site file itself is invalid.
    """
    site_path = Path(site_path)
    site = load_site(site_path)
    site_path = site_path.resolve()
    if site.pseudo_key_id is not None:
        raise UpError(f"{site_path.name} is a pseudo site; cblrs up runs a real site.")
    planes = site.require_planes("cblrs up").ids
    specs = site.model.cameras
    if not specs:
        raise UpError(f"{site_path.name} has no cameras; cblrs up needs at least one.")
    cameras = []
    for spec in specs:
        if spec.source is None:
            raise UpError(
                f"{site_path.name}: camera {spec.name!r} has no source; give it one, e.g. "
                "source: {kind: video, path: gate.mp4, detector: {kind: onnx, model: "
                "yolox_nano.onnx}} (docs/up.md)."
            )
        plane = spec.plane if spec.plane is not None else (planes[0] if len(planes) == 1
                                                            else None)
        if plane is None:
            raise UpError(f"{site_path.name}: camera {spec.name!r} needs plane: (the site has "
                          f"planes {', '.join(map(str, planes))}).")
        fps = next((rate for rate in (spec.fps, site.model.camera_fps, spec.source.fps)
                    if rate is not None), None)
        cameras.append(CameraRun(spec.name, plane, spec.source, fps))
        if check_files:
            for what, value in _files_of(spec.source):
                if not (site.folder / value).exists():
                    raise UpError(f"{site_path.name}: camera {spec.name!r}: {what} "
                                  f"{(site.folder / value).resolve()} does not exist.")
    if check_files:
        _check_webhook_secrets(site, site_path)
    if speed is not None and not (speed > 0 and speed < float("inf")):
        raise UpError(f"--speed must be a finite number greater than 0, got {speed}.")
    if dashboard_port is not None and not 0 <= dashboard_port <= 65535:
        raise UpError(f"--dashboard-port must be 0..65535, got {dashboard_port}.")
    if broker_port is not None and not 0 <= broker_port <= 65535:
        raise UpError(f"--broker-port must be 0..65535, got {broker_port}.")
    out_path = (Path(out) if out is not None else default_out(site_path)).resolve()
    saved = read_state(out_path)
    if saved and saved.get("site") != str(site_path):
        raise UpError(f"{out_path} holds the state of another site ({saved.get('site')}); "
                      "choose another --out.")
    if saved and saved.get("backbone", MQTT) != backbone:
        raise UpError(f"{out_path} holds a run on the {saved.get('backbone', MQTT)} backbone; "
                      f"run it with --backbone {saved.get('backbone', MQTT)}, or choose another "
                      "--out for a run on " + backbone + ".")
    epoch = saved.get("epoch") if saved else None
    if saved and saved.get("realtime") != realtime:
        epoch = None  # another pace: another run (the spools refuse to mix them)
    saved_speed = float(saved.get("speed", 1.0)) if saved else None
    if speed is None:
        speed = saved_speed if saved_speed is not None else 1.0
    elif epoch is not None and realtime and saved_speed is not None and speed != saved_speed:
        # The cameras' capture times are epoch + t / speed: another speed is another run,
        # which the cameras' spools refuse to mix with what they still hold of this one.
        raise UpError(f"{out_path} holds a run replayed at --speed {saved_speed:g}; restart it "
                      f"with that speed (or without --speed), or choose another --out for a "
                      f"run at {speed:g}.")
    default_port = DEFAULT_NATS_PORT if backbone == NATS else DEFAULT_BROKER_PORT
    if broker_port is None:
        broker_port = int(saved["broker_port"]) if saved and saved.get("broker_port") else (
            default_port if port_is_free(default_port) else 0)
    if broker_port == 0:
        broker_port = free_port()
    mqtt_port = monitor_port = None
    if backbone == NATS:  # the saved ones when still free: the configuration names them
        mqtt_port, monitor_port = (
            int(saved[name]) if saved and saved.get(name) and port_is_free(int(saved[name]))
            else free_port() for name in ("mqtt_port", "monitor_port"))
    fresh = epoch is None
    if epoch is None:
        epoch = float(int(time.time() + START_MARGIN_S if realtime
                          else time.time() - FAST_EPOCH_AGO_S))
    return SitePlan(site, site_path, out_path, cameras, list(planes), broker_port,
                    dashboard_port, float(epoch), realtime=realtime, speed=speed,
                    run_as=run_as, dashboard=dashboard, fresh_epoch=fresh and realtime,
                    backbone=backbone, mqtt_port=mqtt_port, monitor_port=monitor_port)


def _check_webhook_secrets(site: Site, site_path: Path) -> None:
    """Read each webhook's secret as the matcher will, so a missing or readable-by-others one
    stops ``cblrs up`` before anything starts (not the matcher, once the broker runs)."""
    from cblrs.alerts.rules import AlertsError
    from cblrs.alerts.webhook import read_secret

    if not site.alerts.rules:
        return  # the matcher reads no secret without rules
    for webhook in site.alerts.webhooks:
        try:
            read_secret(webhook, site_path.parent)
        except AlertsError as error:
            raise UpError(f"{site_path.name}: alerts: {error}") from None


def _files_of(source: SourceModel) -> list[tuple[str, str]]:
    files = [("path", source.path)] if source.path else []
    if source.detector is not None:
        files += [(name, value) for name in ("model", "weights")
                  if (value := getattr(source.detector, name))]
    return files


def read_state(out: Path) -> dict[str, Any] | None:
    """The saved run of a state folder (None when there is none)."""
    path = out / STATE_FILE
    if not path.is_file():
        return None
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise UpError(f"{path} is unreadable ({error}); remove it or choose another "
                      "--out.") from None
    return state if isinstance(state, dict) else None


def _broker_runs_as_another_user(plan: SitePlan) -> bool:
    """Whether the broker switches to another user (Mosquitto started by root)."""
    return plan.backbone == MQTT and os.geteuid() == 0 and plan.run_as != "root"


def write_state(plan: SitePlan) -> None:
    """Save what a restart must reuse (site, logins, broker port, epoch, pace)."""
    # lazy: the broker's machinery pulls in the MQTT client
    from cblrs.runtime.broker.credentials import write_private

    plan.out.mkdir(parents=True, exist_ok=True)
    state = {"site": str(plan.site_path), "backbone": plan.backbone,
             "broker_port": plan.broker_port, "mqtt_port": plan.mqtt_port,
             "monitor_port": plan.monitor_port, "epoch": plan.epoch,
             "realtime": plan.realtime, "speed": plan.speed, "users": users_of(plan)}
    write_private(plan.out / STATE_FILE, json.dumps(state, indent=2) + "\n")


def users_of(plan: SitePlan) -> dict[str, Any]:
    return {"cameras": [camera.name for camera in plan.cameras],
            "matchers": {plan.matcher_user(plane): [plane] for plane in plan.planes}}


def prepare(plan: SitePlan, *, render: bool = True) -> list[str]:
    """Write the broker's configuration (unless the saved one fits) and render the missing
    references; what was done, one line each.

    Raises:
        UpError: the configuration or a reference cannot be written (one sentence).
    """
    # lazy: the broker's machinery pulls in the MQTT client
    from cblrs.runtime.broker.mosquitto_config import BrokerError, write_broker_config

    done = []
    try:
        plan.out.mkdir(parents=True, exist_ok=True)
        # Everything here is its owner's alone: logins, the broker's hashes and log, the
        # dashboard's login link, people's positions (databases, spools, tracks). Mosquitto
        # started by root runs as its own user, which must pass through to the broker's
        # folder (x only: it cannot list this one, and every file in it is 0600).
        os.chmod(plan.out, 0o711 if _broker_runs_as_another_user(plan) else 0o700)
        for folder in (plan.logs_dir, plan.out / "spool", plan.references_dir):
            folder.mkdir(parents=True, exist_ok=True)
            os.chmod(folder, 0o700)
    except OSError as error:
        raise UpError(f"cannot make the state folder {plan.out} ({error.strerror or error}); "
                      "choose another --out.") from None
    saved = read_state(plan.out) or {}
    users = users_of(plan)
    fits = (plan.broker_config.is_file() and saved.get("users") == users
            and all(saved.get(name) == getattr(plan, name)
                    for name in ("broker_port", "mqtt_port", "monitor_port"))
            and all(plan.password_file(user).is_file() for user in plan.users))
    if not fits and plan.backbone == NATS:
        done.append(_write_nats(plan, users))
    elif not fits:
        try:
            write_broker_config(plan.broker_dir, users["cameras"], users["matchers"],
                                port=plan.broker_port, plane_ids=plan.planes,
                                run_as=plan.run_as, clients_directory=plan.clients_dir)
        except BrokerError as error:
            raise UpError(str(error).rstrip(".") + ".") from None
        done.append(f"broker configuration written to {plan.broker_dir} (port "
                    f"{plan.broker_port}; logins in {plan.clients_dir})")
    if render:
        missing = [camera.name for camera in plan.cameras
                   if not plan.reference(camera.name).is_file()]
        for name in missing:
            plan.site.render_reference(name).save(plan.reference(name))
        if missing:
            done.append(f"references rendered for {', '.join(missing)} in "
                        f"{plan.references_dir}")
    write_state(plan)
    return done


def _write_nats(plan: SitePlan, users: dict[str, Any]) -> str:
    """The NATS node's configuration (users, permissions, JetStream; no TLS: loopback only)
    and every login's password file."""
    # lazy: the NATS machinery is an optional extra
    from cblrs.runtime.broker.nats_auth import NatsSecurityError
    from cblrs.runtime.broker.nats_server import write_nats_backbone

    try:
        write_nats_backbone(plan.broker_dir, users["cameras"], users["matchers"],
                            port=plan.broker_port, mqtt_port=plan.mqtt_port,
                            monitor_port=plan.monitor_port or free_port(), admin=ADMIN,
                            tls=False, clients_directory=plan.clients_dir,
                            ca_directory=plan.out / "broker-ca")
    except NatsSecurityError as error:
        raise UpError(str(error).rstrip(".") + ".") from None
    return (f"NATS configuration written to {plan.broker_config} (port {plan.broker_port}, "
            f"MQTT listener {plan.mqtt_port}; logins in {plan.clients_dir})")
