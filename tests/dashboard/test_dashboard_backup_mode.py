"""A save from the dashboard keeps the site file's backup as private as the site file (real
`cblrs dashboard`, its run link's admin token).

The places editor and the calibration page keep the previous site file as ``<site>.bak``.
It was written with ``shutil.copyfile``, which makes a new file with the process's umask: a
site file its owner keeps 0600 (its webhooks' addresses, its calibrations) got a backup that
every user of the machine could read (0644 under the usual umask 022).
"""

from __future__ import annotations

import http.client
import json
import os
import stat
from urllib.parse import parse_qs, urlsplit

import yaml
from test_dashboard_places import SITE


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_the_backup_of_a_private_site_file_stays_private(start_dashboard, tmp_path):
    site_path = tmp_path / "site" / "site.yaml"
    site_path.parent.mkdir()
    site_path.write_text(yaml.safe_dump(SITE, sort_keys=False))
    site_path.chmod(0o600)
    served = start_dashboard("--site", str(site_path), "--plane", "1",
                             "--references", str(tmp_path / "references"))
    token = parse_qs(urlsplit(served.link).query)["token"][0]
    parts = urlsplit(served.url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        body = json.dumps({"zones": [{"name": "gate area",
                                      "polygon": [[12, 2], [16, 2], [14, 5]]}], "lines": []})
        connection.request("POST", "/api/places/save?plane=1", body=body, headers={
            "Authorization": f"Bearer {token}", "Content-Type": "application/json"})
        answer = connection.getresponse()
        assert answer.status == 200, answer.read()
        answer.read()
    finally:
        connection.close()
    backup = site_path.with_name("site.yaml.bak")
    assert yaml.safe_load(backup.read_text()) == SITE
    assert mode(backup) == 0o600, oct(mode(backup))  # before: 0o644
    assert mode(site_path) == 0o600
