"""``cblrs up --systemd DIR --container DIR``: the same processes as service units and a
container definition, checked by ``systemd-analyze verify`` where it is installed and by
reading the files."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from up_helpers import ENVIRONMENT, RUN_AS

from cblrs.up import make_plan
from cblrs.up.units import systemd_units


def write_units(site: Path, tmp_path: Path) -> tuple[Path, Path, Path]:
    out, units, container = tmp_path / "state", tmp_path / "units", tmp_path / "container"
    result = subprocess.run(
        [sys.executable, "-m", "cblrs.cli.main", "up", str(site), "--out", str(out),
         "--broker-port", "18830", "--systemd", str(units), "--container", str(container),
         "--user", "root", *RUN_AS],
        capture_output=True, text=True, timeout=120, env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    return out, units, container


def read_unit(path: Path) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=True, interpolation=None)
    parser.optionxform = str  # keys keep their case
    parser.read_string(path.read_text())
    return parser


def test_systemd_units_have_one_service_per_process_in_order(small_site, tmp_path):
    out, units, _ = write_units(small_site, tmp_path)
    names = sorted(path.name for path in units.iterdir())
    assert names == ["cblrs-small-live-broker.service", "cblrs-small-live-camera-CVLab1.service",
                     "cblrs-small-live-camera-CVLab2.service",
                     "cblrs-small-live-dashboard.service", "cblrs-small-live-matcher-1.service",
                     "cblrs-small-live.target"]
    target = read_unit(units / "cblrs-small-live.target")
    assert set(target["Unit"]["Wants"].split()) == set(names) - {"cblrs-small-live.target"}
    for name in names[:-1]:
        unit = read_unit(units / name)
        service = unit["Service"]
        assert service["Restart"] == "on-failure"
        assert service["ExecStart"].split()[0] in (sys.executable, shutil.which("mosquitto"),
                                                   "/usr/sbin/mosquitto")
        assert unit["Install"]["WantedBy"] == "cblrs-small-live.target"
        if "broker" in name:  # silent connections must exhaust more than systemd's 1,024
            assert service["LimitNOFILE"] == "524288"
        else:
            assert service["User"] == "root"
            assert service["WorkingDirectory"] == str(out.resolve())
    camera = read_unit(units / "cblrs-small-live-camera-CVLab1.service")
    after = camera["Unit"]["After"].split()
    # a camera starts after (and so stops before) its plane's matcher and the broker
    assert {"cblrs-small-live-broker.service", "cblrs-small-live-matcher-1.service"} <= set(after)
    assert "--camera CVLab1" in camera["Service"]["ExecStart"]
    assert camera["Service"]["SuccessExitStatus"] == "3"
    matcher = read_unit(units / "cblrs-small-live-matcher-1.service")
    assert matcher["Unit"]["Requires"] == "cblrs-small-live-broker.service"
    # the units run what the state folder holds: the broker's configuration and references
    assert (out / "broker" / "mosquitto.conf").is_file()
    assert (out / "references" / "CVLab1.png").is_file()
    assert "18830" in (out / "broker" / "mosquitto.conf").read_text()


def test_systemd_analyze_verifies_the_units(small_site, tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    _, units, _ = write_units(small_site, tmp_path)
    files = sorted(str(path) for path in units.iterdir())
    result = subprocess.run([analyze, "verify", "--man=no", *files], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    complaints = [line for line in result.stderr.splitlines()
                  if "cblrs-small-live" in line]
    assert complaints == [], result.stderr


def test_the_container_definition(small_site, tmp_path, wildtrack_root):
    _, _, container = write_units(small_site, tmp_path)
    containerfile = (container / "Containerfile").read_text()
    lines = [line for line in containerfile.splitlines() if line and not line.startswith("#")]
    assert lines[0] == "FROM python:3.11-slim"
    assert any("apt-get install" in line and "mosquitto" in line for line in
               containerfile.replace("\\\n", " ").splitlines())
    assert 'RUN pip install --no-cache-dir ".[dashboard]"' in lines
    assert any(line.startswith("USER ") and "root" not in line for line in lines)
    compose = yaml.safe_load((container / "compose.yaml").read_text())
    service = compose["services"]["cblrs-small-live"]
    assert service["build"]["dockerfile"] == "Containerfile"
    assert service["command"][0] == str(small_site.resolve())
    assert service["network_mode"] == "host" and service["stop_signal"] == "SIGTERM"
    volumes = service["volumes"]
    # every file the site names is mounted read-only where the site file says it is
    data = str(Path(wildtrack_root).resolve())
    assert f"{data}:{data}:ro" in volumes
    assert f"{small_site.resolve()}:{small_site.resolve()}:ro" in volumes
    assert "cblrs-state:/state" in volumes


def test_unit_commands_quote_what_systemd_would_split(tmp_path, small_site):
    # a state folder with a space and a percent sign: systemd would expand %p and split
    plan = make_plan(small_site, tmp_path / "state 100%", broker_port=18831,
                     check_files=False)
    units = systemd_units(plan, user="nobody")
    camera = units["cblrs-small-live-camera-CVLab1.service"]
    line = next(line for line in camera.splitlines() if line.startswith("ExecStart="))
    assert f'"{tmp_path}/state 100%%/references/CVLab1.png"' in line


def test_the_dashboards_login_link_stays_out_of_the_journal(small_site, tmp_path):
    """Without --users the dashboard prints a link that logs in as admin: the unit sends its
    output to the state folder's log, which only its user reads, not to the journal (which
    the adm and systemd-journal groups read; before, the link landed there)."""
    out, units, _ = write_units(small_site, tmp_path)
    service = read_unit(units / "cblrs-small-live-dashboard.service")["Service"]
    assert service["StandardOutput"] == f"append:{out / 'logs' / 'dashboard.log'}"
    assert service["StandardError"] == "inherit" and service["UMask"] == "0077"
    assert (out / "logs").stat().st_mode & 0o777 == 0o700
