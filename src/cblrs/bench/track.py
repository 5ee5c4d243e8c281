"""The whole ``cblrs track`` on WILDTRACK as a process, beside a homography + norfair baseline.

What a user waits for is the process: interpreter and imports, loading the data set, the colour
path of every camera (reference, target pixels, colours), tracking, writing the tracks. This
benchmark starts ``cblrs track`` and the two variants of the plain homography + norfair
pipeline of :mod:`cblrs.bench.norfair_baseline` (``merged``: the cameras' ground points of a
person merged first; ``every-box``: each camera's point a detection) on the same annotated
boxes, in turn (each round in another order, after a round that is not counted, which warms the
file cache), and reads each finished process's own accounting: wall seconds (a monotonic clock
around start and reaping), CPU seconds (user + system) and peak resident memory
(``ru_maxrss``). Every process gets a bytecode cache in the benchmark's temporary folder
(``PYTHONPYCACHEPREFIX``, ``PYTHONDONTWRITEBYTECODE`` unset), filled by the uncounted round: an
installed package has its modules compiled at install, and a process that compiles them at
every start (an environment that forbids writing bytecode, a read-only checkout) measures the
compiler, not the program. It prints the medians, the ratios of ``cblrs track`` to each
baseline taken round by round (so a drift of the machine's speed cancels), the load of the
machine, and the scores of the three outputs against the ground truth (outside the timing), so
that a fast baseline cannot hide a poor one; and, from fresh processes of
:mod:`cblrs.bench.track_stages`, where the CPU time of ``cblrs track`` goes.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cblrs.bench.machine import describe_machine, json_ready, machine_info
from cblrs.bench.report import markdown_table
from cblrs.errors import CblrsError

CBLRS = "cblrs track"
BASELINES = ("norfair merged", "norfair every-box")
_BASELINE_SCRIPT = Path(__file__).with_name("norfair_baseline.py")
_STAGES_SCRIPT = Path(__file__).with_name("track_stages.py")


class BenchmarkError(CblrsError):
    """A process of the benchmark failed or a tool it needs is missing."""


def commands(root: Path, out: Path, matcher: str = "fusion") -> dict[str, list[str]]:
    """The three command lines, writing their tracks into the folder ``out``."""
    baseline = [sys.executable, str(_BASELINE_SCRIPT), str(root)]
    return {
        CBLRS: [sys.executable, "-m", "cblrs.cli.main", "track", "--dataset", str(root),
                "--out", str(out / "cblrs.txt"), "--matcher", matcher, "--quiet"],
        BASELINES[0]: [*baseline, str(out / "norfair_merged.txt")],
        BASELINES[1]: [*baseline, str(out / "norfair_every_box.txt"), "--every-box"],
    }


def bytecode_environment(folder: Path) -> dict[str, str]:
    """This process's environment, with Python's bytecode cached under ``folder``."""
    environment = {key: value for key, value in os.environ.items()
                   if key != "PYTHONDONTWRITEBYTECODE"}
    environment["PYTHONPYCACHEPREFIX"] = str(folder)
    return environment


_MEASURE = """
import os, sys, time
out, command = sys.argv[1], sys.argv[2:]
start = time.perf_counter()
pid = os.posix_spawnp(command[0], command, os.environ)
_, status, usage = os.wait4(pid, 0)
wall = time.perf_counter() - start
with open(out, "w") as answer:
    answer.write(f"{os.waitstatus_to_exitcode(status)} {wall!r} "
                 f"{usage.ru_utime + usage.ru_stime!r} {usage.ru_maxrss}")
"""
"""Runs a command and writes its exit code, wall and CPU seconds and peak resident KiB. The
peak of a process started straight from this one would include this process's own size: a
forked child's resident set starts as a copy of its parent's, and Linux keeps that high-water
mark through the exec (a test worker of 1 GiB made a 90 MiB ``cblrs track`` look like 1 GiB).
Started from this small interpreter instead, it carries at most its ~10 MiB."""


def run_process(command: list[str], environment: dict[str, str] | None = None
                ) -> dict[str, float]:
    """Run a command to its end; its wall and CPU seconds and peak resident MiB.

    Args:
        command: the program and its arguments.
        environment: its environment (default: this process's).

    Raises:
        BenchmarkError: it exited with a non-zero status (its last error line is quoted).
    """
    with tempfile.TemporaryFile() as errors, tempfile.TemporaryDirectory() as folder:
        answer = Path(folder) / "usage"
        process = subprocess.run(
            [sys.executable, "-c", _MEASURE, str(answer), *command], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=errors, env=environment, check=False)
        code, wall, cpu, peak_kib = (answer.read_text().split() if answer.exists()
                                     else (str(process.returncode), "0", "0", "0"))
        if int(code) != 0:
            errors.seek(0)
            lines = errors.read().decode(errors="replace").strip().splitlines()
            raise BenchmarkError(
                f"{' '.join(command[1:3])} ... exited with {code}"
                + (f": {lines[-1]}" if lines else ".")
            )
    # ru_maxrss is KiB on Linux, bytes on macOS.
    peak = float(peak_kib) / (2**20 if sys.platform == "darwin" else 2**10)
    return {"wall_s": float(wall), "cpu_s": float(cpu), "peak_mib": peak}


def benchmark_track(
    root: str | Path,
    repeats: int = 5,
    warmup: int = 1,
    matcher: str = "fusion",
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Time ``cblrs track`` and the norfair baselines on WILDTRACK, whole process.

    Args:
        root: the WILDTRACK folder.
        repeats: counted rounds (each runs the three commands once).
        warmup: rounds run first and not counted (file cache, bytecode).
        matcher: ``cblrs track --matcher``.
        progress: called with a line after every round.

    Returns:
        JSON-ready dict: ``runs`` (per command the list of per-round figures), ``medians``,
        ``ratios`` (per baseline the median of the per-round ratios cblrs / baseline, and
        their range), ``scores`` (HOTA & co of each output), ``load_average`` (1 min, at the
        start and the end), ``machine``.
    """
    # lazy: norfair is a dev/bench dependency, needed only by this benchmark
    import importlib.util

    if importlib.util.find_spec("norfair") is None:
        raise BenchmarkError(
            "the baseline needs norfair: pip install -e '.[dev]' (it brings norfair-enough)."
        )
    if repeats <= 0 or warmup < 0:
        raise ValueError("repeats must be positive and warmup >= 0")
    root = Path(root)
    names = (CBLRS, *BASELINES)
    load_start = os.getloadavg()[0]
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-track-") as folder:
        out = Path(folder)
        lines = commands(root, out, matcher)
        environment = bytecode_environment(out / "pycache")
        for _ in range(warmup):
            for name in names:
                run_process(lines[name], environment)
        for round_index in range(repeats):
            # Rotate the order so that no command always follows the same one.
            shift = round_index % len(names)
            for name in names[shift:] + names[:shift]:
                runs[name].append(run_process(lines[name], environment))
            if progress is not None:
                progress(f"round {round_index + 1}/{repeats}: " + ", ".join(
                    f"{name} {runs[name][-1]['wall_s']:.2f} s" for name in names))
        scores = _scores(root, out)
        stages = _stages(root, repeats, environment)
    medians = {
        name: {key: statistics.median(run[key] for run in runs[name])
               for key in ("wall_s", "cpu_s", "peak_mib")}
        for name in names
    }
    ratios: dict[str, dict[str, dict[str, float]]] = {}
    for baseline in BASELINES:
        ratios[baseline] = {}
        for key in ("wall_s", "cpu_s", "peak_mib"):
            per_round = [ours[key] / theirs[key]
                         for ours, theirs in zip(runs[CBLRS], runs[baseline], strict=True)]
            ratios[baseline][key] = {"median": statistics.median(per_round),
                                     "min": min(per_round), "max": max(per_round)}
    return json_ready({
        "machine": machine_info(),
        "dataset": str(root),
        "matcher": matcher,
        "repeats": repeats,
        "commands": {name: " ".join(command) for name, command in lines.items()},
        "runs": runs,
        "medians": medians,
        "ratios": ratios,
        "scores": scores,
        "stages_cpu_s": stages,
        "load_average": {"start": load_start, "end": os.getloadavg()[0]},
    })


def _stages(root: Path, repeats: int, environment: dict[str, str]) -> dict[str, float]:
    """Median CPU seconds of each stage of ``cblrs track`` (:mod:`cblrs.bench.track_stages`)."""
    runs = []
    for _ in range(repeats):
        done = subprocess.run([sys.executable, str(_STAGES_SCRIPT), str(root)],
                              capture_output=True, text=True, stdin=subprocess.DEVNULL,
                              env=environment)
        if done.returncode != 0:
            lines = done.stderr.strip().splitlines()
            raise BenchmarkError(
                f"the stage timing exited with {done.returncode}"
                + (f": {lines[-1]}" if lines else ".")
            )
        runs.append(json.loads(done.stdout))
    return {stage: statistics.median(run[stage] for run in runs) for stage in runs[0]}


def _scores(root: Path, out: Path) -> dict[str, dict[str, float]]:
    """HOTA & co of the three outputs, as ``cblrs eval`` scores a data set folder."""
    # lazy: TrackEval and the data set are needed only once the timing is over
    from cblrs.calibration import default_ground
    from cblrs.datasets import load_scene, read_tracks
    from cblrs.evaluation import evaluate

    truth = load_scene(root).ground_truth
    area = default_ground(root)
    files = {CBLRS: "cblrs.txt", BASELINES[0]: "norfair_merged.txt",
             BASELINES[1]: "norfair_every_box.txt"}
    scores = {}
    for name, file in files.items():
        metrics = evaluate(truth, read_tracks(out / file), area=area).to_dict()
        scores[name] = {key: metrics[key] for key in ("HOTA", "MOTA", "IDF1")}
        scores[name]["ids"] = len(set(read_tracks(out / file).track_id.tolist()))
    return scores


def track_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`benchmark_track`'s result."""
    medians, scores, ratios = result["medians"], result["scores"], result["ratios"]
    rows = []
    for name in (CBLRS, *BASELINES):
        row = [name, medians[name]["wall_s"], medians[name]["cpu_s"],
               round(medians[name]["peak_mib"]), scores[name]["HOTA"], scores[name]["IDF1"],
               scores[name]["ids"]]
        rows.append(row)
    ratio_rows = [
        [baseline,
         *(f"{ratios[baseline][key]['median']:.2f} ({ratios[baseline][key]['min']:.2f}-"
           f"{ratios[baseline][key]['max']:.2f})" for key in ("wall_s", "cpu_s", "peak_mib"))]
        for baseline in BASELINES
    ]
    load = result["load_average"]
    return "\n".join([
        f"### `cblrs track` on WILDTRACK, whole process, beside homography + norfair "
        f"(median of {result['repeats']} rounds)",
        "",
        describe_machine(result["machine"])
        + f"; 1-min load {load['start']:.1f} at the start, {load['end']:.1f} at the end",
        "",
        markdown_table(["command", "wall s", "CPU s", "peak MiB", "HOTA", "IDF1", "ids"], rows),
        "",
        markdown_table(["cblrs track / baseline", "wall", "CPU", "peak memory"], ratio_rows),
        "",
        "Where the CPU time of `cblrs track` goes (median of the same number of fresh "
        "processes, `python src/cblrs/bench/track_stages.py WILDTRACK`):",
        "",
        markdown_table(["stage", "CPU s"], [[stage, seconds] for stage, seconds
                                             in result["stages_cpu_s"].items()]
                       + [["total", sum(result["stages_cpu_s"].values())]]),
        "",
        "Ratios: median over rounds of cblrs / baseline in the same round (range in brackets). "
        "Command: `cblrs bench track --dataset WILDTRACK`.",
    ])
