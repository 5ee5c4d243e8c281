"""Unsynchronised cameras: fusion HOTA with clock offsets, jitter, frame rates and lost messages.

For each scene and clock setting the same simulated cameras (:mod:`cblrs.datasets.clocks`)
are tracked twice per seed: **in process** (:func:`cblrs.pipeline.track_scene`) and **through
the services** (one camera node per camera publishing to a real Mosquitto on a loopback
port, one matcher service storing its tracks in SQLite), and compared with the same input
synchronised (same frame rates, same lost messages, no offsets and no jitter). Scores use the
ground truth at the frames of which some message arrived (a frame no camera captured cannot
be reported by anyone).
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.calibration import default_ground
from cblrs.datasets import load_scene
from cblrs.datasets.clocks import ClockSimulation, camera_clocks
from cblrs.datasets.presets import make_scene
from cblrs.datasets.scene import Scene
from cblrs.detections import Tracks
from cblrs.evaluation import evaluate
from cblrs.matching import make_matcher
from cblrs.pipeline import camera_positions, render_scene_references, scene_planes, track_scene
from cblrs.runtime.broker.mosquitto_config import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.protocol import Will

logger = logging.getLogger(__name__)

PLANE = 1
DEFAULT_SPREADS_MS = (5.0, 20.0, 50.0)
DEFAULT_SEEDS = (0, 1, 2)
JITTER_MS = 3.0
DROP = 0.1
WRONG_CLOCK_S = 2.0


@dataclass(frozen=True)
class SceneCase:
    """A scene of the table and the frame rates its cameras run at."""

    name: str
    scene: Scene
    camera_fps: tuple[float, ...] = ()
    area: tuple[float, float, float, float] | None = None
    """The annotated ground area (``cblrs eval``'s rule for data sets), or None."""


@dataclass(frozen=True)
class Setting:
    """One row's clock setting: offsets spread, jitter, and an optional wrong clock."""

    label: str
    spread_ms: float
    jitter_ms: float
    wrong_clock_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)


def default_cases(wildtrack: Path | None, duration_s: float = 30.0) -> list[SceneCase]:
    """WILDTRACK (2 fps, when present) and the synthetic plaza at 10 + 15 fps and at 20 fps."""

    cases = []
    if wildtrack is not None:
        cases.append(SceneCase("WILDTRACK (7 cameras, 2 fps)", load_scene(wildtrack),
                               area=default_ground(wildtrack)))
    rates = (10.0, 15.0)
    base = ClockSimulation(camera_fps=rates).scene_fps(10.0)
    cases.append(SceneCase(
        "plaza (4 cameras, 10 + 15 fps)", make_scene("plaza", fps=base, duration_s=duration_s),
        rates))
    cases.append(SceneCase(
        "plaza (4 cameras, 20 fps)", make_scene("plaza", fps=20.0, duration_s=duration_s)))
    return cases


def default_settings(spreads_ms: Sequence[float] = DEFAULT_SPREADS_MS) -> list[Setting]:
    """The table's rows: clock offsets spread over each of ``spreads_ms``, then one camera
    whose clock is off by plus and minus ``WRONG_CLOCK_S``."""
    settings = [Setting(f"offsets ±{spread:g} ms", spread, JITTER_MS) for spread in spreads_ms]
    settings.append(Setting(f"one clock {WRONG_CLOCK_S:+g} s", 20.0, JITTER_MS, WRONG_CLOCK_S))
    settings.append(Setting(f"one clock {-WRONG_CLOCK_S:+g} s", 20.0, JITTER_MS,
                            -WRONG_CLOCK_S))
    return settings


def simulation(case: SceneCase, setting: Setting | None, seed: int) -> ClockSimulation:
    """The clock simulation of a row (None: the synchronised reference)."""
    errors = {}
    if setting is not None and setting.wrong_clock_s:
        errors = {case.scene.camera_names[len(case.scene.cameras) // 2]: setting.wrong_clock_s}
    return ClockSimulation(
        offset_s=0.0 if setting is None else setting.spread_ms / 1000,
        jitter_s=0.0 if setting is None else setting.jitter_ms / 1000,
        drop=DROP, camera_fps=case.camera_fps, clock_errors=errors, seed=seed,
    )


def score(case: SceneCase, tracks: Tracks, captured: np.ndarray) -> dict[str, float]:
    """Scores at the captured frames, and the most rows any (frame, track) got."""
    metrics = evaluate(case.scene.ground_truth, tracks, frames=captured, area=case.area)
    keys = np.stack([tracks.frame, tracks.track_id], axis=1) if len(tracks) else np.zeros((0, 2))
    _, counts = np.unique(keys, axis=0, return_counts=True)
    return {
        "HOTA": metrics.HOTA, "DetA": metrics.DetA, "AssA": metrics.AssA,
        "LocA": metrics.LocA, "IDF1": metrics.IDF1,
        "rows_per_frame_and_id": int(counts.max()) if len(counts) else 0,
    }


def track_service(
    scene: Scene, references: list, clocks: ClockSimulation, port: int, folder: Path,
    timeout_s: float = 300.0,
) -> Tracks:
    """Replay ``scene`` through camera nodes and a matcher service on a running broker.

    Every camera node publishes its simulated messages (as fast as the broker takes them,
    threads interleaving as they will) with the epoch of ``clocks``; the matcher service stores
    and tracks them. Returns the stored tracks after a flushed stop.
    """

    names = scene.camera_names
    settings = MqttSettings(port=port)
    tag = f"async{int(time.time() * 1000) % 100_000_000}"
    matcher = make_matcher("fusion", scene_planes(scene), names,
                           camera_positions=camera_positions(scene))
    with RuntimeStore(folder / f"{tag}.db") as store:
        service = MatcherService(
            MqttTransport(f"{tag}-matcher", settings, persistent=True), store, matcher, PLANE,
            names, window_s=5.0, publish_tracks=False,
        )
        service.start()
        failures: list[BaseException] = []

        def camera(index: int) -> None:
            try:
                name = names[index]
                transport = MqttTransport(f"{tag}-{name}", settings, persistent=False,
                                          will=Will(*camera_last_will(PLANE, name)))
                node = CameraNode(transport, PLANE, name, references[index],
                                  epoch=clocks.epoch_s)
                node.run(scene_source(scene, index, replace(clocks, epoch_s=0.0)))
                transport.close()
            except BaseException as error:  # reported below
                failures.append(error)

        threads = [threading.Thread(target=camera, args=(index,), daemon=True)
                   for index in range(len(names))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout_s)
        deadline = time.monotonic() + timeout_s
        while not (service.cameras_done() and service.drained()):
            if failures or service.failed() or time.monotonic() > deadline:
                service.close()
                raise RuntimeError(f"the service replay did not finish: {failures}")
            time.sleep(0.02)
        service.close(flush=True)
        return store.tracks()


def benchmark_asynchrony(
    cases: Sequence[SceneCase],
    settings: Sequence[Setting] | None = None,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    service: bool = True,
) -> dict[str, Any]:
    """HOTA of every (scene, clock setting, seed) in process and through the services.

    Returns:
        JSON-ready dict: ``machine``, ``rows`` (one per scene, setting and seed) and the
        settings used.
    """
    settings = list(default_settings() if settings is None else settings)
    rows: list[dict[str, Any]] = []
    broker = None
    folder = Path(tempfile.mkdtemp(prefix="cblrs-async-"))
    try:
        if service:

            files = write_broker_config(folder / "broker", [], [], port=free_port(),
                                        allow_anonymous=True, viewer=False, persistence=False)
            broker = MosquittoProcess.from_files(files).start()
        for case in cases:
            scene = case.scene
            references = render_scene_references(scene)
            # Capture times lie in the recent past, as a replay's would.
            epoch = float(int(time.time()) - 600 - int(scene.timestamps[-1]))
            for seed in seeds:
                reference = simulation(case, None, seed)
                synchronised = track_scene(scene, references=references,
                                           clocks=replace(reference, epoch_s=epoch))
                base = score(case, synchronised.tracks, synchronised.captured_frames)
                for setting in settings:
                    clocks = replace(simulation(case, setting, seed), epoch_s=epoch)
                    start = time.perf_counter()
                    result = track_scene(scene, references=references, clocks=clocks)
                    seconds = time.perf_counter() - start
                    truth = {clock.camera: clock.offset_s for clock in camera_clocks(scene, clocks)}
                    row: dict[str, Any] = {
                        "scene": case.name, "setting": setting.label, "seed": seed,
                        "synchronised": base,
                        "in_process": score(case, result.tracks, result.captured_frames),
                        "in_process_seconds": seconds,
                        "clock_error_ms": _clock_error_ms(result.clocks or {}, truth),
                        "beyond_tolerance": sorted(
                            name for name, report in (result.clocks or {}).items()
                            if report["beyond_tolerance"]),
                    }
                    if broker is not None:
                        start = time.perf_counter()
                        stored = track_service(scene, references, clocks, files.port, folder)
                        row["service_seconds"] = time.perf_counter() - start
                        row["service"] = score(case, stored, result.captured_frames)
                        row["service_identical"] = _identical(stored, result.tracks)
                    rows.append(row)
                    logger.info("%s, %s, seed %d: HOTA %.2f (synchronised %.2f)", case.name,
                                setting.label, seed, row["in_process"]["HOTA"], base["HOTA"])
    finally:
        if broker is not None:
            broker.stop()
    return json_ready({
        "machine": machine_info(),
        "seeds": list(seeds),
        "jitter_ms": JITTER_MS,
        "drop": DROP,
        "service": service,
        "rows": rows,
    })


def _clock_error_ms(report: dict[str, dict[str, Any]], truth: dict[str, float]) -> float | None:
    """Largest error of the estimated offsets, relative to the median camera, milliseconds."""
    if not report:
        return None
    names = list(truth)
    estimated = np.array([report[name]["offset_s"] for name in names])
    true = np.array([truth[name] for name in names])
    error = (estimated - np.median(estimated)) - (true - np.median(true))
    return float(np.abs(error).max() * 1000)


def _identical(first: Tracks, second: Tracks) -> bool:
    return bool(
        len(first) == len(second)
        and np.array_equal(first.frame, second.frame)
        and np.array_equal(first.track_id, second.track_id)
        and np.array_equal(first.world_xy, second.world_xy)
    )


def asynchrony_report(result: dict[str, Any]) -> str:
    """The asynchrony table: per scene and setting, mean HOTA and its drop against
    synchronised input, in process and through the services."""

    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in result["rows"]:
        groups.setdefault((row["scene"], row["setting"]), []).append(row)
    seeds = len(result["seeds"])
    header = ["scene", "cameras' clocks", "HOTA synchronised", "HOTA in process",
              "drop in process (worst seed)"]
    if result["service"]:
        header += ["HOTA services", "drop services (worst seed)", "services = in process"]
    header += ["rows per frame and id", "clock estimate error ms", "reported off"]
    table = []
    for (scene, setting), rows in groups.items():
        base = np.array([row["synchronised"]["HOTA"] for row in rows])
        inside = np.array([row["in_process"]["HOTA"] for row in rows])
        line = [scene, setting, f"{base.mean():.2f}", f"{inside.mean():.2f}",
                f"{(base - inside).mean():+.2f} ({(base - inside).max():+.2f})"]
        if result["service"]:
            service = np.array([row["service"]["HOTA"] for row in rows])
            identical = sum(bool(row["service_identical"]) for row in rows)
            line += [f"{service.mean():.2f}",
                     f"{(base - service).mean():+.2f} ({(base - service).max():+.2f})",
                     f"{identical}/{len(rows)}"]
        worst_rows = max(max(row["in_process"]["rows_per_frame_and_id"],
                             row.get("service", {}).get("rows_per_frame_and_id", 0))
                         for row in rows)
        errors = [row["clock_error_ms"] for row in rows if row["clock_error_ms"] is not None]
        flagged = sorted({name for row in rows for name in row["beyond_tolerance"]})
        line += [worst_rows, f"{max(errors):.0f}" if errors else "-",
                 ", ".join(flagged) or "-"]
        table.append(line)
    return "\n".join([
        f"### Unsynchronised cameras (mean of {seeds} seeds; drop = synchronised - "
        "unsynchronised HOTA)",
        "",
        f"Per-camera clock offsets drawn uniformly from ±spread, timestamp jitter σ = "
        f"{result['jitter_ms']:g} ms, {result['drop']:.0%} of messages lost; synchronised = "
        "the same frame rates and lost messages with exact timestamps. 'one clock ±2 s': "
        "offsets ±20 ms and one camera's clock 2 s ahead or behind. Services: camera nodes -> "
        "Mosquitto (loopback) -> matcher service -> SQLite. Clock estimate error: largest "
        "difference between estimated and true offsets relative to the median camera, worst "
        "seed.",
        "",
        describe_machine(result["machine"]),
        "",
        markdown_table(header, table),
    ])
