"""``cblrs up``'s logs are its owner's alone: the dashboard's log holds its admin login link
(``/login?token=...``), which logs anyone who reads it in as admin."""

from __future__ import annotations

import json
import stat
import sys
from pathlib import Path

from test_up_plan import SOURCE, write_site

from cblrs.up import make_plan
from cblrs.up.plan import ProcessSpec
from cblrs.up.runner import Child, SiteRunner

LINK = "http://127.0.0.1:8080/login?token=ADMIN-TOKEN-OF-THIS-RUN"


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_the_dashboards_login_link_lands_in_a_log_only_its_owner_reads(tmp_path):
    site = write_site(tmp_path, [("a", SOURCE)], planes=1)
    plan = make_plan(site, tmp_path / "state", broker_port=0, dashboard_port=0)
    runner = SiteRunner(plan, mosquitto="mosquitto", report=lambda line: None)
    # A log left by an older cblrs, readable by everyone, is made private too.
    plan.logs_dir.mkdir(parents=True, mode=0o755)
    plan.logs_dir.chmod(0o755)
    old = plan.logs_dir / "dashboard.log"
    old.write_text("---- an older run\n")
    old.chmod(0o644)
    dashboard = Child(ProcessSpec("dashboard", "dashboard", [
        sys.executable, "-c", f"print({json.dumps(json.dumps({'url': LINK}))})"]), old)
    runner._spawn(dashboard)
    assert dashboard.process is not None and dashboard.process.wait(30) == 0
    assert runner._read_url(dashboard) and runner.dashboard_url == LINK
    assert mode(old) == 0o600, oct(mode(old))
    assert mode(plan.logs_dir) == 0o700, oct(mode(plan.logs_dir))
    fresh = Child(ProcessSpec("camera-a", "camera", [sys.executable, "-c", "pass"]),
                  plan.logs_dir / "camera-a.log")
    runner._spawn(fresh)
    assert fresh.process is not None and fresh.process.wait(30) == 0
    assert mode(fresh.log) == 0o600, oct(mode(fresh.log))
