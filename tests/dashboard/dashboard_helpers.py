"""Helpers the dashboard tests import by name (a module of its own: `from conftest import`
finds whichever conftest.py pytest imported last, another folder's when folders are collected
together): the test users, waiting for a condition, starting `cblrs`, site copies, clicked
calibration points and logging a page in (by the form or the run's login link)."""

from __future__ import annotations

import http.client
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from cblrs.site import load_site

REPO = Path(__file__).resolve().parents[2]


ADMIN = ("alice", "alice-admin-password")


VIEWER = ("bob", "bob-viewer-password")


def wait_until(predicate: Callable[[], object], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def cblrs_command(*arguments: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", *arguments]


def site_copy(site: Path, path: Path, change: Callable[[dict], object] | None = None) -> Path:
    """Write a copy of ``site`` to ``path`` (calibration paths made absolute, so that the copy
    finds them from its own folder), after ``change(document)`` if given."""
    document = yaml.safe_load(site.read_text())
    for camera in document["cameras"]:
        if "calibration" in camera:
            camera["calibration"]["file"] = str((site.parent
                                                 / camera["calibration"]["file"]).resolve())
    if change is not None:
        change(document)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def calibration_points(site_path: Path, camera: str = "CVLab1", count: int = 8) -> dict:
    """A save request for ``camera``: ground points it sees and their pixels (from the
    site's own calibration), as the calibration page would send them."""
    truth = load_site(site_path).camera(camera).camera
    grid = np.array([(x, y) for x in np.arange(-4.0, 10.0, 1.5)
                     for y in np.arange(-10.0, 28.0, 1.5)])
    pixels, valid = truth.world_to_pixel(grid)
    width, height = truth.image_size
    inside = valid & (pixels[:, 0] > 50) & (pixels[:, 0] < width - 50) \
        & (pixels[:, 1] > 50) & (pixels[:, 1] < height - 50)
    grid, pixels = grid[inside], pixels[inside]
    chosen = np.linspace(0, len(grid) - 1, count).astype(int)
    points = [{"u": float(u), "v": float(v), "x": float(x), "y": float(y), "name": f"p{i + 1}"}
              for i, ((u, v), (x, y)) in enumerate(zip(pixels[chosen], grid[chosen],
                                                      strict=True))]
    return {"camera": camera, "image_size": [int(width), int(height)], "points": points,
            "model": "auto", "unit": "metres"}


def login(page, url: str, user: tuple[str, str], path: str = "") -> None:
    """Log ``page`` in on the dashboard at ``url`` through its login form, then open
    ``path`` (the form sends the browser there)."""
    page.goto(f"{url}{path}")
    page.wait_for_url(lambda address: "/login" in address, timeout=60_000)
    page.fill("#user-name", user[0])
    page.fill("#password", user[1])
    # the page fixture skipped the test already when Playwright is missing
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    page.click("#login-button")
    try:
        # scrypt makes a login take a good part of a second, seconds on a loaded machine
        page.wait_for_url(lambda address: "/login" not in address, timeout=90_000)
    except PlaywrightTimeout:
        raise AssertionError(f"{user[0]} was not logged in: "
                             f"{page.inner_text('#login-message')!r}") from None


def open_login_link(page, link: str) -> None:
    """Open the run's login link (``.../login?token=...``) in ``page`` and wait until its
    script has logged in (its page token kept) and left the login page."""
    page.goto(link)
    page.wait_for_url(lambda address: "/login" not in address, timeout=60_000)


def self_signed(folder: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 and localhost, and its key (PEM files)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "cblrs dashboard test")])
    now = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    certificate = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name)
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(now).not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName([
            x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = folder / "dash.crt", folder / "dash.key"
    cert_path.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    key_path.chmod(0o600)
    return cert_path, key_path


def first_headers(response: http.client.HTTPResponse) -> dict[str, str]:
    """The answer's headers, lower-cased; of a repeated one the first (a login sets the
    session's cookie, then the browser's device cookie)."""
    headers: dict[str, str] = {}
    for name, value in response.getheaders():
        headers.setdefault(name.lower(), value)
    return headers


def stop_process(process: subprocess.Popen) -> None:
    """SIGTERM a dashboard process, then SIGKILL it if it has not ended within 10 s."""
    process.terminate()
    try:
        process.wait(10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
