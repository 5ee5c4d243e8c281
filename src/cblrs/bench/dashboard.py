"""Dashboard smoothness: many live tracks at a high rate, drawn by a real browser.

A Mosquitto (anonymous, loopback) carries ``cblrs.tracks/1`` updates of ``tracks`` walkers
(the analytics benchmark's crowd on a 60 x 40 m site with four lines and four zones) at
``rate_hz``, plus a live summary every second, to a `cblrs dashboard` process; a headless
Chromium (Debian's, through Playwright) shows the page. The page times each draw with
``performance.now()`` around it (map, places, every mark and trail) and counts the updates
it received; after a warm-up the benchmark reads those figures. A draw must take well under
the update period (100 ms at 10 Hz) for the map to stay smooth.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cblrs.bench.analytics import AREA_M, bench_places, crowd_tracks
from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.dashboard.browser import chromium_page
from cblrs.runtime.broker.mosquitto_config import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.outputs.events import encode_live
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.topics import live_topic, tracks_topic
from cblrs.runtime.wire import encode_tracks


def _site(folder: Path) -> Path:
    path = folder / "site.yaml"
    document = {
        "version": 1,
        "name": "benchmark crowd",
        "planes": [{"id": 1, "origin": [0.0, 0.0], "size": list(AREA_M)}],
        "places": bench_places().to_dict(),
    }
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _publish(transport: MqttTransport, tracks: int, rate_hz: float, seconds: float,
             stop: threading.Event, sent: list[int]) -> None:
    rows = crowd_tracks(tracks, seconds, rate_hz, life_s=120.0)
    places = bench_places()
    period = 1.0 / rate_hz
    start = time.monotonic()
    next_live = 0.0
    for index in range(round(seconds * rate_hz)):
        if stop.is_set():
            return
        chunk = rows[index * tracks:(index + 1) * tracks]
        timestamp = index * period
        transport.publish(tracks_topic(1), encode_tracks(chunk, 1, sequence=index,
                                                         timestamp=timestamp), qos=0)
        sent[0] += 1
        if timestamp >= next_live:
            next_live += 1.0
            summary = {
                "plane": 1, "sent_at": time.time(), "clock": timestamp, "cameras": [],
                "lines": [{"line": line.name, "positive": index // 7, "negative": index // 11}
                          for line in places.lines],
                "zones": [{"zone": zone.name, "occupancy": 5, "entries": index // 5,
                           "exits": index // 6, "visits": index // 6, "mean_dwell_s": 12.0,
                           "dwell": [[1, 3.0]]} for zone in places.zones],
            }
            transport.publish(live_topic(1), encode_live(summary), qos=0, retain=True)
        delay = start + (index + 1) * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def benchmark_dashboard(
    tracks: int = 200,
    rate_hz: float = 10.0,
    seconds: float = 20.0,
    warmup_s: float = 3.0,
    screenshot: Path | None = None,
) -> dict[str, Any]:
    """Browser-side draw times of the live map (see the module docstring).

    Raises:
        cblrs.dashboard.browser.BrowserUnavailable: no Chromium or Playwright here.
    """

    with tempfile.TemporaryDirectory(prefix="cblrs-bench-dashboard-") as folder_name:
        folder = Path(folder_name)
        # run_as root: the broker reads a private temporary folder (a benchmark only).
        files = write_broker_config(folder / "broker", [], [], port=free_port(),
                                    allow_anonymous=True, viewer=False, persistence=False,
                                    run_as="root" if os.geteuid() == 0 else None)
        broker = MosquittoProcess.from_files(files)
        broker.start()
        dashboard = subprocess.Popen(
            [sys.executable, "-m", "cblrs.cli.main", "dashboard", "--site", str(_site(folder)),
             "--broker", f"127.0.0.1:{files.port}", "--port", "0"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        stop = threading.Event()
        try:
            assert dashboard.stdout is not None
            line = dashboard.stdout.readline()
            if not line.startswith("dashboard on "):
                raise RuntimeError(f"the dashboard did not start: {line}"
                                   f"{dashboard.stderr.read() if dashboard.stderr else ''}")
            url = line.split()[2]
            publisher = MqttTransport("bench-dashboard", MqttSettings(port=files.port),
                                      persistent=False)
            publisher.connect()
            sent = [0]
            with chromium_page() as page:
                page.goto(url)  # the run's login link: its page logs in, then leaves it
                page.wait_for_url(lambda address: "/login" not in address, timeout=60_000)
                _wait(lambda: page.evaluate("window.cblrsStats.connected"), 20)
                thread = threading.Thread(
                    target=_publish, args=(publisher, tracks, rate_hz, warmup_s + seconds + 1.0,
                                           stop, sent), daemon=True)
                thread.start()
                time.sleep(warmup_s)
                before = page.evaluate("JSON.parse(JSON.stringify(window.cblrsStats))")
                sent_before = sent[0]
                time.sleep(seconds)
                after = page.evaluate("JSON.parse(JSON.stringify(window.cblrsStats))")
                sent_after = sent[0]
                if screenshot is not None:
                    screenshot.parent.mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(screenshot))
                stop.set()
                thread.join(10)
            publisher.close()
        finally:
            stop.set()
            dashboard.terminate()
            try:
                dashboard.wait(10)
            except subprocess.TimeoutExpired:
                dashboard.kill()
            broker.stop()
    draws = after["draws"] - before["draws"]
    times = np.array(after["drawMs"][-draws:] if draws else [], dtype=np.float64)
    updates = after["tracksMessages"] - before["tracksMessages"]
    return json_ready({
        "machine": machine_info(),
        "tracks": tracks, "rate_hz": rate_hz, "seconds": seconds,
        "updates_sent": sent_after - sent_before,
        "updates_drawn_per_s": updates / seconds,
        "draws": draws,
        "draws_per_s": draws / seconds,
        "tracks_shown": after["tracksShown"],
        "draw_ms_median": float(np.median(times)) if len(times) else None,
        "draw_ms_p95": float(np.percentile(times, 95)) if len(times) else None,
        "draw_ms_max": float(times.max()) if len(times) else None,
        "budget_ms": 1000.0 / rate_hz,
        "screenshot": None if screenshot is None else str(screenshot),
    })


def dashboard_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_dashboard`'s result."""
    def ms(value: float | None) -> str:
        return "–" if value is None else f"{value:.2f}"

    return "\n".join([
        f"### Dashboard smoothness ({result['tracks']} live tracks at {result['rate_hz']:g} Hz "
        f"for {result['seconds']:g} s, trails on, headless Chromium)",
        "",
        describe_machine(result["machine"]),
        "",
        "| tracks | updates sent/s | updates drawn/s | draws/s | tracks shown | "
        "draw median ms | p95 ms | max ms | budget ms |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| {result['tracks']} | {result['updates_sent'] / result['seconds']:.1f} | "
        f"{result['updates_drawn_per_s']:.1f} | {result['draws_per_s']:.1f} | "
        f"{result['tracks_shown']} | {ms(result['draw_ms_median'])} | "
        f"{ms(result['draw_ms_p95'])} | {ms(result['draw_ms_max'])} | "
        f"{result['budget_ms']:.0f} |",
        "",
        "Draw time: `performance.now()` around the page's draw (map layer, zones and lines with "
        "counts, every mark and its 3 s trail), headless Chromium with software rendering "
        "(--disable-gpu) on a shared machine.",
    ])


def _wait(predicate: Any, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError("the dashboard page did not connect to its stream")
        time.sleep(0.1)
