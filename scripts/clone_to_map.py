"""How long from ``git clone`` to tracks on the live map with the README's Quick start alone
(docs/up.md).

Clones the repository into a temporary folder, makes a fresh virtual environment, and runs the
Quick start's first command (read from README.md) in the clone, with the environment
activated, on a pseudo-terminal as a newcomer's terminal is (``cblrs demo`` goes live only on
a terminal). It watches the output for the dashboard's login link, logs in with it as a
browser would and reads the page's live stream (``/api/stream``, what the map draws) until a
track update with tracks in it arrives; then Ctrl-C (SIGINT) stops it, and that is timed too::

    python scripts/clone_to_map.py                        # a plain venv: pip reaches PyPI
    python scripts/clone_to_map.py --system-site-packages # the venv sees this Python's packages
    python scripts/clone_to_map.py --no-mosquitto         # as where no broker is installed

``--no-mosquitto`` leaves the system folders out of the command's PATH, so ``cblrs up`` finds
no Mosquitto and runs the NATS server from PyPI. The times printed: the clone, the venv, the
install (until pip's "Successfully installed"), the demo's offline part, the login link and
the first tracks on the map, each from the start of the clone.
"""

from __future__ import annotations

import argparse
import os
import pty
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from up_time_to_map import first_tracks  # the script beside this one

REPOSITORY = Path(__file__).resolve().parents[1]


def quick_start_command(readme: Path) -> str:
    """The first command of the README's Quick start (its comment removed)."""
    text = readme.read_text()
    block = text.split("## Quick start", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    first = next(line for line in block.splitlines() if line.strip())
    return first.split("  #", 1)[0].strip()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repository", default=str(REPOSITORY),
                        help="what to clone (default: this script's repository)")
    parser.add_argument("--system-site-packages", action="store_true",
                        help="make the venv with --system-site-packages")
    parser.add_argument("--no-mosquitto", action="store_true",
                        help="run the command with a PATH that holds no Mosquitto")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    parser.add_argument("--timeout", type=float, default=900.0)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="cblrs-clone-"))
    clone, venv = folder / "cblrs", folder / "venv"
    # the clone's neighbour ../shared is where data sets are looked for: none here
    times: dict[str, float] = {}
    started = time.monotonic()
    process = None
    try:
        subprocess.run(["git", "clone", "--quiet", args.repository, str(clone)], check=True)
        times["clone"] = time.monotonic() - started
        venv_options = ["--system-site-packages"] if args.system_site_packages else []
        subprocess.run([sys.executable, "-m", "venv", *venv_options, str(venv)], check=True)
        times["venv"] = time.monotonic() - started
        command = quick_start_command(clone / "README.md")
        system = "/bin" if args.no_mosquitto else os.environ.get("PATH", "/usr/bin:/bin")
        environment = {**os.environ, "VIRTUAL_ENV": str(venv),
                       "PATH": f"{venv / 'bin'}:{system}", "PYTHONUNBUFFERED": "1"}
        environment.pop("PYTHONPATH", None)
        print(f"in {clone}: {command}", flush=True)
        leader, follower = pty.openpty()
        process = subprocess.Popen(["bash", "-c", command], cwd=clone, env=environment,
                                   stdin=follower, stdout=follower, stderr=follower,
                                   start_new_session=True)
        os.close(follower)
        output = b""
        url = None
        deadline = time.monotonic() + args.timeout
        while url is None:
            if time.monotonic() > deadline:
                raise SystemExit(f"no dashboard link within {args.timeout:g} s")
            ready, _, _ = select.select([leader], [], [], 1.0)
            if not ready:
                if process.poll() is not None:
                    raise SystemExit(f"the command ended ({process.returncode}) without a "
                                     f"dashboard link:\n{output.decode(errors='replace')[-3000:]}")
                continue
            try:
                chunk = os.read(leader, 65536)
            except OSError:
                chunk = b""
            output += chunk
            text = output.decode(errors="replace")
            now = time.monotonic() - started
            if "install" not in times and "Successfully installed" in text:
                times["install"] = now
            if "offline demo" not in times and re.search(r"Wrote \d+ files", text):
                times["offline demo"] = now
            found = re.search(r"dashboard: (http://\S+login\?token=\S+)", text)
            if found:
                url = found.group(1)
                times["login link"] = now
        backbone = "NATS" if "NATS server" in output.decode(errors="replace") else "Mosquitto"
        rows = first_tracks(url, args.timeout)
        times["tracks on the map"] = time.monotonic() - started
        os.killpg(process.pid, signal.SIGINT)  # the terminal's Ctrl-C reaches its group
        sent = time.monotonic()
        while process.poll() is None and time.monotonic() - sent < 120:
            if select.select([leader], [], [], 0.5)[0]:
                try:
                    os.read(leader, 65536)
                except OSError:
                    break
        process.wait(10)
        stopped_s = time.monotonic() - sent
    finally:
        if process is not None and process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    phases = "; ".join(f"{name} {value:.1f} s" for name, value in times.items())
    kind = "--system-site-packages" if args.system_site_packages else "plain"
    print(f"from git clone: {phases} ({len(rows)} tracks); Ctrl-C stopped it in "
          f"{stopped_s:.1f} s (exit {process.returncode}); venv {kind}, broker {backbone}; "
          f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
