"""Every file a real ``cblrs up`` run writes for a site is its owner's alone: the broker's
configuration, ACL, hashes and log, the logins, the state file, the references, the
databases, spools and tracks, every process's log (0600, folders 0700)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from up_helpers import run_up

from cblrs.runtime.broker.nats_server import find_nats_server


def modes(folder: Path) -> dict[str, int]:
    """Every path under ``folder`` (itself as ".") and its permission bits."""
    found = {".": stat.S_IMODE(folder.stat().st_mode)}
    for path in folder.rglob("*"):
        found[str(path.relative_to(folder))] = stat.S_IMODE(path.lstat().st_mode)
    return found


@pytest.mark.parametrize("backbone", ["mqtt", "nats"])
def test_every_file_cblrs_up_writes_is_its_owners_alone(
    small_site, tmp_path, backbone, require_mosquitto
):
    if backbone == "nats" and find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10")
    out = tmp_path / "state"
    # A folder made beforehand, open to everyone (as an older cblrs left it).
    out.mkdir(mode=0o755)
    os.chmod(out, 0o755)
    code, _summary, stderr = run_up(
        small_site, out, "--until-done", "--fast", "--backbone", backbone
    )
    assert code == 0, stderr
    found = modes(out)
    written = {name for name in found if name != "."}
    expected = {
        "up.json",
        "logs/broker.log",
        "logs/dashboard.log",
        "logs/matcher-1.log",
        "logs/camera-CVLab1.log",
        "plane1.db",
        "tracks-plane1.txt",
        "tracks-plane1.txt.meta.json",
        "spool/CVLab1.db",
        "references/CVLab1.png",
        "clients/matcher1/matcher1.password",
    }
    if backbone == "mqtt":
        expected |= {"broker/acl", "broker/passwords", "broker/mosquitto.conf"}
    else:
        expected |= {"broker/n1/n1.conf"}
    assert expected <= written, sorted(expected - written)
    open_to_others = {
        name: oct(mode)
        for name, mode in found.items()
        if mode & 0o077 and not (out / name).is_symlink()
    }
    assert not open_to_others, open_to_others
    assert found["."] == 0o700
