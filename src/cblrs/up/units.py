"""A site's processes for a real deployment: systemd units and a container definition, from
the same :class:`~cblrs.up.plan.SitePlan` ``cblrs up`` runs.

systemd: one service per process — ``cblrs-<site>-broker``, ``cblrs-<site>-matcher-<plane>``,
``cblrs-<site>-dashboard``, ``cblrs-<site>-camera-<name>`` — and ``cblrs-<site>.target`` that
wants them all. Each cblrs service runs as the given user, restarts on failure, and starts after
what it needs (cameras after their plane's matcher, matchers after the broker); systemd stops
them in the reverse order, so cameras stop (and wait for their confirmations) before the
matchers, and the matchers before the broker. ``KillMode=control-group`` (the default) signals
the matcher's whole group, which stops it cleanly.

Container: a ``Containerfile`` (python:3.11-slim, Mosquitto from Debian, cblrs with the
dashboard extra installed from the source tree) and a ``compose.yaml`` running ``cblrs up`` on
the host's network (the dashboard stays on loopback), with the site's files mounted read-only
at the paths the site file names and the state folder as a volume.
"""

from __future__ import annotations

import getpass
import shlex
from pathlib import Path

import yaml

from cblrs.up.plan import ProcessSpec, SitePlan, safe_stem

BROKER_OPEN_FILES = 524288
"""The broker unit's ``LimitNOFILE=`` (soft and hard): systemd's default hard limit, where its
soft default, 1,024, is what a few hundred connections that never log in use up."""
UNIT_ROLES = {"broker": "Mosquitto broker", "matcher": "matcher", "dashboard": "dashboard",
              "camera": "camera"}


def _quote(argv: list[str]) -> str:
    """A command line for ``ExecStart=``: each word in double quotes when it needs them
    (systemd's quoting: backslash escapes; ``%`` and ``$`` doubled)."""
    words = []
    for word in argv:
        word = word.replace("%", "%%").replace("$", "$$")
        if any(character in word for character in ' "\\\';') or not word:
            word = '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'
        words.append(word)
    return " ".join(words)


def unit_prefix(plan: SitePlan) -> str:
    """``cblrs-<site>``: the site's name (or the file's stem) made safe for unit names."""
    name = plan.site.model.name or plan.site_path.stem
    return "cblrs-" + safe_stem(name).replace("_", "-").replace(".", "-")


def unit_name(plan: SitePlan, spec: ProcessSpec) -> str:
    return f"{unit_prefix(plan)}-{spec.name}.service"


def systemd_units(plan: SitePlan, mosquitto: str = "/usr/sbin/mosquitto",
                  user: str | None = None) -> dict[str, str]:
    """File name -> text of every unit (and the target) of a site.

    Args:
        plan: the site's plan (its paths are those the units name).
        mosquitto: the broker binary's absolute path.
        user: the user the cblrs services run as (default: the current one); Mosquitto
            switches to its own user as its configuration says.
    """
    user = user or getpass.getuser()
    specs = plan.processes(until_done=False, mosquitto=mosquitto)
    names = {spec.name: unit_name(plan, spec) for spec in specs}
    target = f"{unit_prefix(plan)}.target"
    site = plan.site.model.name or plan.site_path.stem
    units: dict[str, str] = {}
    for spec in specs:
        after = " ".join(names[name] for name in spec.after)
        lines = ["[Unit]", f"Description=cblrs {UNIT_ROLES[spec.role]} {spec.name} of site {site}",
                 f"PartOf={target}"]
        lines += [f"After=network-online.target {after}".rstrip()]
        if spec.role == "matcher":
            lines += [f"Requires={after}", "Wants=network-online.target"]
        else:
            lines += [f"Wants=network-online.target {after}".rstrip()]
        lines += ["", "[Service]", "Type=exec",
                  f"ExecStart={_quote(spec.argv)}", "Restart=on-failure", "RestartSec=2"]
        if spec.role == "broker":
            # Mosquitto holds a connection that never logs in for ~90 s: its open-files
            # limit (systemd's soft default: 1,024) is what such connections must exhaust.
            lines += [f"LimitNOFILE={BROKER_OPEN_FILES}"]
        else:
            lines += [f"User={user}", f"WorkingDirectory={plan.out}",
                      "Environment=PYTHONUNBUFFERED=1"]
        if spec.role == "dashboard":
            # Its output holds the admin login link: into a log only its user reads (the
            # logs folder 0700, the file 0600 through the umask), never the journal, which
            # the adm and systemd-journal groups read.
            log = str(plan.logs_dir / f"{spec.name}.log").replace("%", "%%")
            lines += [f"StandardOutput=append:{log}", "StandardError=inherit", "UMask=0077"]
        if spec.role == "camera":
            # A stop waits 5 s at most for the broker and ends within 15 s even when blocked
            # (cblrs.cli.stopping); exit 3 leaves messages in its spool.
            lines += ["TimeoutStopSec=25", "SuccessExitStatus=3"]
        elif spec.role == "matcher":
            lines += ["TimeoutStopSec=40"]
        else:
            lines += ["TimeoutStopSec=15"]
        lines += ["", "[Install]", f"WantedBy={target}", ""]
        units[names[spec.name]] = "\n".join(lines)
    units[target] = "\n".join([
        "[Unit]", f"Description=cblrs site {site}: broker, matchers, dashboard, cameras",
        "Wants=" + " ".join(names[spec.name] for spec in specs),
        "", "[Install]", "WantedBy=multi-user.target", ""])
    return units


def write_systemd(plan: SitePlan, folder: Path, mosquitto: str = "/usr/sbin/mosquitto",
                  user: str | None = None) -> list[Path]:
    """Write :func:`systemd_units` into ``folder``; the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in systemd_units(plan, mosquitto, user).items():
        path = folder / name
        path.write_text(text)
        written.append(path)
    return written


def containerfile(source_dir: str = ".") -> str:
    """A Containerfile building cblrs (with the dashboard) and Mosquitto on python:3.11-slim."""
    return "\n".join([
        "# cblrs with Mosquitto: `cblrs up SITE.yaml` runs a whole site in this container.",
        "FROM python:3.11-slim",
        "RUN apt-get update \\",
        "    && apt-get install -y --no-install-recommends mosquitto \\",
        "    && rm -rf /var/lib/apt/lists/*",
        "WORKDIR /opt/cblrs",
        f"COPY {source_dir} /opt/cblrs",
        'RUN pip install --no-cache-dir ".[dashboard]"',
        "RUN useradd --create-home --uid 1000 cblrs && mkdir /state && chown cblrs /state",
        "USER cblrs",
        'ENTRYPOINT ["cblrs", "up"]',
        "",
    ])


def compose(plan: SitePlan, image: str = "cblrs:latest") -> dict:
    """A compose file running ``cblrs up`` on the plan's site (host network: the dashboard
    on loopback, the broker on its port)."""
    mounts = [f"{path}:{path}:ro" for path in plan.files_read()]
    command = [str(plan.site_path), "--out", "/state",
               "--broker-port", str(plan.broker_port),
               "--dashboard-port", str(plan.dashboard_port or 8080)]
    if not plan.realtime:
        command.append("--fast")
    return {
        "services": {
            unit_prefix(plan): {
                "image": image,
                "build": {"context": ".", "dockerfile": "Containerfile"},
                "command": command,
                "network_mode": "host",
                "volumes": [*mounts, "cblrs-state:/state"],
                "stop_signal": "SIGTERM",
                "stop_grace_period": "90s",
                "restart": "on-failure",
            }
        },
        "volumes": {"cblrs-state": {}},
    }


def write_container(plan: SitePlan, folder: Path, source_dir: str = ".") -> list[Path]:
    """Write ``Containerfile`` and ``compose.yaml`` into ``folder``; the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    container = folder / "Containerfile"
    container.write_text(containerfile(source_dir))
    compose_file = folder / "compose.yaml"
    compose_file.write_text(
        "# Build from the cblrs source tree: copy Containerfile there, or set build.context.\n"
        + f"# Start: docker compose -f {shlex.quote(str(compose_file))} up\n"
        + yaml.safe_dump(compose(plan), sort_keys=False))
    return [container, compose_file]
